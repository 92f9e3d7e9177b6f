"""Geometry as data and the code that makes it: the BioTac, the nine indenters (and later the testbed)."""
