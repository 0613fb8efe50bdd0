from opt2skill.cli.app import main

main()
