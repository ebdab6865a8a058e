"""The Velodyne VLP-16 (``scanner.Lidar``) and its ray culling and casting kernels."""
