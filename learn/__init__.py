"""Electrode models and learned tactile mappings.

Torch-free at import: `learn.synthetic` (and `fe.electrodes`, the physics-based electrode model it uses)
are numpy only; the torch models live in their own modules and are imported on use.
"""
