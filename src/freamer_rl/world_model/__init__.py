"""RSSM world model, imagination env + policy optimisation, and KL anomaly detection (paper Appendix J).

* :mod:`.rssm` -- :class:`RSSM` (Eqs. A23-A25), :class:`WorldModel` (loss Eq. A27); helpers in :mod:`.functional`,
  default encoder/decoder in :mod:`.obs_nets`, :func:`train_world_model` in :mod:`.training`.
* :mod:`.heads` -- symlog two-hot heads, head ensembles, DreamerV3's percentile return scale (issue 22 options).
* :mod:`.metrics` -- reconstruction MSE, imagination horizon, seed latents (evaluation of a trained world model).
* :mod:`.imagination` -- :class:`RSSMWorldModelEnv` (a TorchRL ``ModelBasedEnvBase``), :class:`ImaginationPPO`.
* :mod:`.anomaly` -- :class:`KLAnomalyDetector`, :class:`KLAnomalyTransform`, :func:`plot_anomaly_timeline` (J.5).
* :mod:`.bench_imagination` -- imagined steps/s vs TorchRL's ``DreamerEnv`` (``python -m`` it; not imported here).
"""

from freamer_rl.world_model import anomaly
from freamer_rl.world_model.anomaly import *  # noqa: F403
from freamer_rl.world_model.functional import action_to_onehot, free_nats_kl, gaussian_kl, symexp, symlog
from freamer_rl.world_model.heads import HeadEnsemble, PercentileReturnScale, TwoHotHead, twohot_decode, twohot_encode
from freamer_rl.world_model.imagination import ImaginationPPO, RSSMWorldModelEnv, valid_imagination_mask
from freamer_rl.world_model.obs_nets import MLPObsDecoder, MLPObsEncoder
from freamer_rl.world_model.rssm import RSSM, WorldModel
from freamer_rl.world_model.training import as_sequences, train_world_model

# the public names of the submodules (``DANGER_HR`` stays in :mod:`.anomaly`)
__all__ = [
    "RSSM",
    "WorldModel",
    "MLPObsEncoder",
    "MLPObsDecoder",
    "gaussian_kl",
    "free_nats_kl",
    "symlog",
    "symexp",
    "action_to_onehot",
    "TwoHotHead",
    "HeadEnsemble",
    "PercentileReturnScale",
    "twohot_encode",
    "twohot_decode",
    "as_sequences",
    "train_world_model",
    "RSSMWorldModelEnv",
    "ImaginationPPO",
    "valid_imagination_mask",
    *(name for name in anomaly.__all__ if name != "DANGER_HR"),
]
