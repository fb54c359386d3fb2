"""Datasets on disk (docs/design.md §3): reading, validating and writing them; ``synth/`` makes them."""
