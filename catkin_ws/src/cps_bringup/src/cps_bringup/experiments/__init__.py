"""The paper's experiments reproduced with this system (make experiments)."""
