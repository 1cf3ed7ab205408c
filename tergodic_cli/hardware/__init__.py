"""Real-hardware backends (Franka, F/T sensors, RealSense) behind the robot Protocols; each an optional extra."""
