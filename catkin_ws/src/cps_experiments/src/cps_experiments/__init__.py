"""The missions as a user runs them (make demo, make monitor), their reports, and the paper's experiments."""
