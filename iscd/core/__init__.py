"""The core below everything: the config loader, the air interface, errors, the compiled-kernel cache."""
