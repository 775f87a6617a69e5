"""The rig: acquisition from the cameras, pairing, the shared-memory ring (drivers -> ring buffer)."""
