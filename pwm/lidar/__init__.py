"""Laser altimetry on arrays: shots (pwm.lidar.shots), their tracks' strip adjustment to a model and
a shape model from adjusted spots. No files and no catalog here (readers in pwm.io.lidar)."""
