"""Geometry: camera and rig models, calibrated stereo pairs, and geodesy (Earth and Mars frames,
the local vertical, map CRSs)."""
