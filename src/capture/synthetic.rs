//! Synthetic renderer of rigs (being built under issue 3).
