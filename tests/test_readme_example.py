"""The README's "compose the layers in your own TorchRL pipeline" snippet runs as written."""

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_compose_example_runs():
    text = README.read_text()
    section = text.split("## Compose the layers in your own TorchRL pipeline", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope: dict = {}
    exec(compile(code, str(README), "exec"), scope)
    rollout = scope["rollout"]
    assert rollout.batch_size == (16,) or rollout.batch_size[0] <= 16
    assert torch.isfinite(rollout["action_log_prob"]).all()
    assert scope["loss"].__class__.__name__ == "ClipPPOLoss"
