"""Decode: frames handed in, records out (tracking -> luminance -> demodulation; patches -> disparity -> range). Imports no drivers, rig, outputs, service or command line."""
