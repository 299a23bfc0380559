"""Configuration: the one recipe loader (YAML, dotted overrides, typed dataclasses, range tables) and the sections
every trainer shares (``env``, ``collector``, ``logging``, ``run``, ``optim``). Knows no trainer and no model."""
