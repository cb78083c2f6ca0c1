"""The fits of ``coiltrack calibrate`` (``fits``) and the distortion survey (``survey``)."""
