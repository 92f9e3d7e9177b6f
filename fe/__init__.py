"""Finite elements of the BioTac skin, fluid and contact, written in warp-lang."""
