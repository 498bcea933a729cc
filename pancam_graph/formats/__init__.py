"""Other tools' file formats, read and written: ROS bags, KITTI, GPS logs, calibrations, images,
trajectory files (TUM, KITTI, GeoJSON, KML) and plain CSV/JSON tables."""
