"""The command line (``iscd``): :mod:`.main` and one module per command in :mod:`.commands`."""
