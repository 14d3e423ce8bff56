"""The ``semantic3d`` command line: a typer app, one module per command group."""
