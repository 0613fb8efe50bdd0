import sys

from opt2skill.trajopt.native import main

sys.exit(main())
