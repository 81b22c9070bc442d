"""Pixels to geometry: frames and cameras, segmentation, keypoints, object SDFs, overlays."""
