"""The `opt2skill` command. Each area registers its commands from its own module."""
