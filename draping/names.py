"""The names draping accepts for garments, motions and body phenotypes, in one torch-free home.

The modules that own each concept (:mod:`draping.garments`, :mod:`draping.motion`,
:mod:`draping.body`) re-export these tuples; the command-line parsers import them from here so
that ``--help`` never loads torch.
"""

from __future__ import annotations

__all__ = ["GARMENTS", "MOTIONS", "PHENOTYPES"]

#: Garment templates made by :func:`draping.garments.make_garment`.
GARMENTS = ("tshirt", "tank", "longsleeve", "dress", "skirt", "pants", "shorts")

#: Procedural motions made by :func:`draping.motion.generate` (``random``: a seeded random
#: smooth motion).
MOTIONS = ("walk", "arms", "squat", "turn", "jacks", "random")

#: The six Anny phenotype parameters, each in [0, 1], in the order of a shape vector.
PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")
