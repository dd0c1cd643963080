"""Garment draping and cloth optimisation on polygeo's geometry (GAPS, OneFit, GarNet, FNOpt)."""
