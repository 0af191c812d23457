"""Graph nodes: thin wiring of the pure algorithm modules onto the bus."""
