"""Stereo vision for the in-hand map: rectification, disparity, 3D points, texture, calibration."""
