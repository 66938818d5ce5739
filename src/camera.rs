//! Camera model (being built under issue 2).
