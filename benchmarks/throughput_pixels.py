"""The pixel path's reference code against its fast code, interleaved in one process (A B A B ...).

    OMP_NUM_THREADS=1 python benchmarks/throughput_pixels.py --rounds 5 --parts encoder render collect

Three parts, each timed ``--rounds`` times per path, the two paths alternating within a round (old first in even
rounds, new first in odd ones); every ratio is new/old speed of the same round, and the median over rounds is
reported (the machine may be shared: only ratios measured side by side mean anything). Times are the process's
CPU time (``time.process_time``), with one torch thread.

* ``encoder``: the recipes' ``VisionEncoder`` (CNN backbone + Slot Attention, ``model.embed_dim`` 128, 4 slots) at
  their shapes: the update's forward+backward on a ``ppo.minibatch_size`` = 512 minibatch (``[32, 16]`` sequences)
  and the collection's no-grad forward on one step of ``env.num_envs`` frames (eval mode). MiniGrid
  (``minigrid_redundant_views``): 56x56 frames, 2 slot iterations, 16 envs; Crafter (``crafter_cpu``): 64x64
  frames, 3 iterations, 8 envs. Old path: ``SlotAttention.fast = False`` and out-of-place ReLUs.
* ``render``: ``MiniGridEnv.frame()`` on MultiRoom-N2-S4 (``fast_render`` False: MiniGrid's ``get_frame``; True:
  ``render_pov``), microseconds per frame over random play.
* ``collect``: collection frames/s of a FreamerV1 trainer built from ``recipes/minigrid_redundant_views.yaml``
  (``ppo.frames_per_batch`` = ``--frames``), one batch per path per round after a warm-up batch on each; the old
  path switches every fast path off (the three above).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from freamer_rl.layers.encoders import CNNBackbone, VisionEncoder
from freamer_rl.layers.slot_attention import SlotAttention

ROOT = Path(__file__).resolve().parents[1]
MINIGRID_RECIPE = ROOT / "recipes" / "minigrid_redundant_views.yaml"
#: (name, frame side, slot iterations, envs per collection step) of the two pixel recipes
ENCODER_CASES = (("minigrid_redundant_views", 56, 2, 16), ("crafter_cpu", 64, 3, 8))


def set_fast(modules, fast: bool) -> None:
    """Switch every fast path of the model(s) on or off: Slot Attention's iterations and the CNN's in-place ReLUs."""
    for root in modules:
        for m in root.modules():
            if isinstance(m, SlotAttention):
                m.fast = fast
            elif isinstance(m, CNNBackbone):
                for layer in m.net:
                    if isinstance(layer, nn.ReLU):
                        layer.inplace = fast


def _alternate(rounds: int, run_old, run_new) -> list[tuple[float, float]]:
    """Per round (old seconds, new seconds), the order alternating between rounds."""
    out = []
    for r in range(rounds):
        if r % 2 == 0:
            old, new = run_old(), run_new()
        else:
            new, old = run_new(), run_old()
        out.append((old, new))
    return out


def _timed(fn) -> float:
    """CPU seconds of this process spent in ``fn()`` (less disturbed than wall time when other jobs share the
    cores: waiting for a core is not counted; one torch thread, the envs in this process)."""
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


def _summary(label: str, pairs: list[tuple[float, float]], unit: str, scale: float) -> str:
    old = statistics.median(p[0] for p in pairs) * scale
    new = statistics.median(p[1] for p in pairs) * scale
    ratio = statistics.median(p[0] / p[1] for p in pairs)
    spread = [round(p[0] / p[1], 2) for p in pairs]
    return f"{label:58s} old {old:9.1f} {unit}  new {new:9.1f} {unit}  speed-up x{ratio:.2f} (rounds {spread})"


def _encoder_case(name: str, side: int, iters: int, envs: int, rounds: int, minibatch: int) -> list[str]:
    """Both encoder timings of one recipe's shapes (see the module docstring)."""
    torch.manual_seed(0)
    enc = VisionEncoder(CNNBackbone(3), out_dim=128, num_slots=4, slot_iters=iters).eval()
    train_px = torch.randint(0, 256, (minibatch // 16, 16, side, side, 3), dtype=torch.uint8)
    step_px = torch.randint(0, 256, (envs, side, side, 3), dtype=torch.uint8)

    def update(fast: bool) -> float:
        set_fast([enc], fast)
        enc.zero_grad(set_to_none=True)
        return _timed(lambda: enc(train_px).square().mean().backward())

    def collect(fast: bool, steps: int = 20) -> float:
        set_fast([enc], fast)

        def run():
            with torch.no_grad():
                for _ in range(steps):
                    enc(step_px)

        return _timed(run) / steps

    update(True), update(False), collect(True), collect(False)  # warm-up (allocator, oneDNN primitives)
    pairs = _alternate(rounds, lambda: update(False), lambda: update(True))
    lines = [_summary(f"{name}: encoder fwd+bwd [{minibatch // 16}, 16, {side}, {side}, 3]", pairs, "ms", 1e3)]
    pairs = _alternate(rounds, lambda: collect(False), lambda: collect(True))
    lines.append(_summary(f"{name}: encoder no-grad step [{envs}, {side}, {side}, 3]", pairs, "ms", 1e3))
    return lines


def bench_encoder(rounds: int, minibatch: int = 512) -> list[str]:
    lines = []
    for name, side, iters, envs in ENCODER_CASES:
        lines += _encoder_case(name, side, iters, envs, rounds, minibatch)
    return lines


def bench_render(rounds: int, frames: int = 300) -> list[str]:
    from freamer_rl_envs.minigrid import make_minigrid_env

    env = make_minigrid_env("MiniGrid-MultiRoom-N2-S4-v0", pixels=True, seed=0)
    env.reset()
    raw = env._unwrapped
    rng = np.random.default_rng(0)
    states = []  # the same sequence of states for both paths: replay the actions after a reseeded reset

    def run(fast: bool) -> float:
        env.fast_render = fast
        raw.reset(seed=0)
        total = 0.0
        for i in range(frames):
            if len(states) <= i:
                states.append(int(rng.integers(6)))
            total += _timed(env.frame)  # only the rendering, not the step
            _, _, terminated, truncated, _ = raw.step(states[i])
            if terminated or truncated:
                raw.reset()
        return total / frames

    run(True), run(False)
    pairs = _alternate(rounds, lambda: run(False), lambda: run(True))
    env.close()
    return [_summary("MultiRoom-N2-S4: MiniGridEnv.frame() 56x56", pairs, "us", 1e6)]


def bench_collect(rounds: int, frames: int) -> list[str]:
    from freamer_rl.trainers.minigrid_ppo import Trainer
    from freamer_rl.trainers.registry import load_config
    from freamer_rl_envs.minigrid import MiniGridEnv

    threads = torch.get_num_threads()
    cfg = load_config(str(MINIGRID_RECIPE), [f"ppo.frames_per_batch={frames}", "logging.progress_bar=false"])
    run_dir = Path(tempfile.mkdtemp(prefix="throughput_pixels_"))
    try:
        trainer = Trainer(cfg, run_dir / "run", resume=False)
        torch.set_num_threads(threads)
        # the policy lives in trainer.modules (FreamerModules, a dataclass); the loss modules hold references to it
        models = [trainer.modules.actor_value, *(v for v in vars(trainer).values() if isinstance(v, nn.Module))]
        if not any(isinstance(m, SlotAttention) for root in models for m in root.modules()):
            raise RuntimeError("found no SlotAttention in the trainer's modules: the A/B would time one path twice")
        collector = trainer.make_collector((2 * rounds + 2) * frames)
        it = iter(collector)

        def batch(fast: bool) -> float:
            set_fast(models, fast)
            MiniGridEnv.fast_render = fast
            return _timed(lambda: next(it))

        batch(True), batch(False)  # warm-up (compilation of the DNC step, first resets)
        pairs = _alternate(rounds, lambda: batch(False), lambda: batch(True))
        collector.shutdown()
    finally:
        MiniGridEnv.fast_render = True
        shutil.rmtree(run_dir, ignore_errors=True)
    fps = [(frames / o, frames / n) for o, n in pairs]
    old, new = statistics.median(f[0] for f in fps), statistics.median(f[1] for f in fps)
    ratio = statistics.median(o / n for o, n in pairs)
    return [
        f"{'minigrid_redundant_views: collection frames/s (' + str(frames) + ' frames/batch)':58s} old {old:9.1f} fps"
        f"   new {new:9.1f} fps   speed-up x{ratio:.2f} (rounds {[round(o / n, 2) for o, n in pairs]})"
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--frames", type=int, default=512, help="collection frames per batch (part 'collect')")
    parser.add_argument("--parts", nargs="+", default=["encoder", "render", "collect"])
    args = parser.parse_args(argv)
    unknown = set(args.parts) - {"encoder", "render", "collect"}
    if unknown:
        parser.error(f"--parts: unknown {sorted(unknown)}; choose from encoder, render, collect")
    torch.set_num_threads(args.threads)
    lines = [f"torch {torch.__version__}, {args.threads} thread(s), {args.rounds} rounds, medians"]
    for part in args.parts:
        if part == "encoder":
            lines += bench_encoder(args.rounds)
        elif part == "render":
            lines += bench_render(args.rounds)
        else:
            lines += bench_collect(args.rounds, args.frames)
        print("\n".join(lines), flush=True)  # a script: partial results as each part ends
        lines = []


if __name__ == "__main__":
    main()
