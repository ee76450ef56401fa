"""The `odometry` stage: radar-inertial odometry (EKF-RIO) at radar scan times."""
