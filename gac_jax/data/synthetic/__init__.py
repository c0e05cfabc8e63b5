"""Procedural KITTI-format driving scenes (object detection + depth layouts)."""
