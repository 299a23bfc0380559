"""Print the parameter table (trainable vs frozen per component; the paper's Table 4) for a recipe.

    python benchmarks/param_table.py                                   # default offline recipe
    python benchmarks/param_table.py recipes/minigrid_multiroom_n2s4_clip.yaml \
        model.vision.clip_pretrained=null model.vision.allow_random_weights=true   # counts only, no weights needed
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recipe", nargs="?", default=str(ROOT / "recipes" / "minigrid_multiroom_n2s4.yaml"))
    ap.add_argument("overrides", nargs="*")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    from freamer_rl.cli import main as cli_main

    sys.exit(cli_main(["params", args.recipe, *args.overrides, *(["--markdown"] if args.markdown else [])]))


if __name__ == "__main__":
    main()
