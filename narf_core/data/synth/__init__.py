"""Procedural articulated tools and their pybullet ground-truth renders (``narf synth``)."""
