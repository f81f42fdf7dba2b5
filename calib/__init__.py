"""pallet6d.calib: camera intrinsics, camera-to-vehicle extrinsics and their calibration."""
