"""``python -m semantic3d``: the command line."""

from semantic3d.cli.app import main

main()
