"""The per-capture stages of `hemicube reconstruct`, in order: alignment, extraction, decode, fine-tuning, fitting."""
