"""The command line: the `hamid` app, one thin layer over the Python API (`main` is
its entry point). The only subpackage that imports click or knows exit codes."""

from hamid.cli.app import main

__all__ = ["main"]
