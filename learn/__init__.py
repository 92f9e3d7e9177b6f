"""Electrode models and learned tactile mappings.

Torch-free at import: `learn.electrode_physics` (the physics-based electrode model) and
`learn.synthetic` are numpy only; the torch models live in their own modules and are imported on use.
"""
