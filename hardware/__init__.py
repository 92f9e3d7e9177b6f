"""Real testbed drivers (YuMi EGM + RWS, Weiss KMS40, BioTac over SPI), simulated devices that speak the
same wire protocols on loopback, and `hardware.backend.HardwareBackend` (see docs/hardware.md)."""
