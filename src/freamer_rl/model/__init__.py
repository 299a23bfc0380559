"""FreamerV1 assembly (paper Sections 3-4): model config, modality registry, factory, heads, auxiliary losses,
weight transfer, parameter table. Built from the layers in :mod:`freamer_rl.layers`."""
