"""The benchmark suite behind silcr bench."""
