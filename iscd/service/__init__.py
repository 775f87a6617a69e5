"""The daemon: the frame loop, its stats, sd_notify, the overload policy."""
