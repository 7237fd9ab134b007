"""Physical twin: PyBullet simulation of the heterogeneous inspection fleet in an industrial hall, publishing what real robot drivers publish."""
