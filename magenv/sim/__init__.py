"""The simulated world: gimbal, magnet, fields and sensors."""
