"""Live viser viewer built on a render function."""
