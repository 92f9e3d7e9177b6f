"""Weiss KMS40 F/T sensor: ASCII protocol (`protocol`), streaming driver (`client`), simulator (`sim`)
and its `[kms40]` config section, which opens it as a `hardware.ft_sensor.ForceTorqueSensor` (`config`)."""
