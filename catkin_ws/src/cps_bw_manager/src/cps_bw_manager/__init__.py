"""Digital tissue, part 2: the bandwidth manager (rate allocation by a linear program, solved exactly by weighted water-filling)."""
