"""python -m cosy_cli: the cosy command."""

from .cli.main import cli

if __name__ == "__main__":
    cli()
