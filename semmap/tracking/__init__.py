"""Multi-object tracking in the image: BoT-SORT (with camera-motion compensation) and SORT."""
