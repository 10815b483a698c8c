"""Subcommand groups of the `rig` CLI: one module per group, each with `register(subparsers)`."""
