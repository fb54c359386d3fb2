"""Datasets on disk (DESIGN §3): reading, validating and writing them; ``synth/`` makes them."""
