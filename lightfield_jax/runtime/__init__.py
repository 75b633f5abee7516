"""Process resources below every layer: memory estimates and limits, timing, progress lines."""
