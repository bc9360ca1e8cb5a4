"""Camera calibration: ChArUco intrinsics, extrinsics in the robot base frame, the rig file."""
