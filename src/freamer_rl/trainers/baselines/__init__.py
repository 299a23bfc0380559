"""TorchRL baselines through the project's run loop, recipes and runner: PPO-MLP / PPO-CNN, IMPALA, DreamerV3."""
