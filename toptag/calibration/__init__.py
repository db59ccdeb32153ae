"""Camera calibration on site (`toptag calibrate`): intrinsics from board views, extrinsics from
surveyed control points or AprilTag ground plates, a re-check after maintenance, and the calibration
covariance that every fix carries."""
