"""Subcommands of the ``iscd`` console command.

Each module here defines ``register(sub)``, which adds its parser to the argparse
subparsers object ``sub`` and sets ``func`` (``args -> int`` exit status) as default.
"""

COMMANDS = ("run", "replay", "simulate", "calibrate", "info", "tx", "devices", "bench", "eval", "campaign", "config")
