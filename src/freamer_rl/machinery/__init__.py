"""Training machinery of the paper (App. A, G, K): reward shaping, reward mixer, exploration bonuses, success buffer,
OGM-GE, mission parsers. Each piece plugs into a trainer from its recipe section; none imports a trainer."""
