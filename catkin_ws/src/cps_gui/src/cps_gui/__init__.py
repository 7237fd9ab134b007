"""Digital twin, part 2: the operator GUI, an rqt-style plugin that also runs standalone."""
