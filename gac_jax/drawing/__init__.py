"""Pictures: detections (boxes, detection_pictures), tracks (track_pictures), depth maps
(depth_pictures), and the grid that tiles them with the PNG writer (picture_grid)."""
