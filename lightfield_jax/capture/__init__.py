"""Real captures: image I/O, exposure brackets, calibration, detection, patterns, inspection."""
