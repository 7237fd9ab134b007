"""Digital tissue, part 2: the bandwidth manager (rate allocation by linear program) and a real shaped network link between two namespaces."""
