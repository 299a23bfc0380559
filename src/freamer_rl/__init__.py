"""freamer_rl: FreamerV1 (filter-before-mixing) as TorchRL-native components."""

__version__ = "0.1.0"
