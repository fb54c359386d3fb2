"""Radiance fields: a part field per rigid link and the configuration-conditioned field."""
