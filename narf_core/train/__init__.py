"""Two-stage training: part fields (stage 1), then distillation into the configuration field (stage 2)."""
