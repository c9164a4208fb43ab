"""Subcommands of the ``vi3`` CLI, one module each."""
