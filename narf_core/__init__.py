"""NARF: neural articulated radiance fields for pose and configuration estimation (NARF22)."""

__version__ = "0.1.0"
