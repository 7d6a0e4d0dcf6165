"""firmware_sim: a MuJoCo emulator of a PX4-style flight controller and a depth camera speaking MAVLink."""
