"""The `accel-jax` command (placeholder; subcommands arrive with the report)."""

import click


@click.group()
def main():
    """accel-jax: servo accelerometer design studies."""
