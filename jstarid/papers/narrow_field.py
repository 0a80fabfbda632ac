"""The narrow twin: a simulated copy of a real narrow, deep star tracker (the any-camera setting).

The real camera (a test set of another project, kept outside the repository): 1392×1040 px,
6.1° × 4.6° field, ≈ 15.8″/px, 40–130 detections per frame down to V ≈ 10, ≈ 0.8 px centroid
noise, up to 2 false stars. Its camera is the ``narrow_twin`` preset; its frames are
:data:`NOISE`. The goal on it (each algorithm with its defaults): ≥ 95 % of frames identified, no
mis-identified frame in 1,000, ≥ 100 frames/s for MLV and RpNet on 2 cores.
"""

CAMERA = "narrow_twin"
MAG_LIMIT = 10.0  # Hipparcos to V 10: complete to V ≈ 8, so fainter real stars are missing
CAPACITY = 128  # detections kept per frame (≈ 2 % of frames have more)
#: The twin's frames: centroid noise (px), brightness scatter (mag), two false stars of V 6–10.
NOISE = {"position_sigma_px": 0.8, "magnitude_sigma": 0.2, "n_false": 2,
         "false_mag_min": 6.0, "false_mag_max": 10.0}
