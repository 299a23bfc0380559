"""PAMAP2 wearable-sensor data: loader, observation features and a format-faithful synthetic generator.

Paper: Section 5 and Appendix C (observation = IMU 36 dims + heart-rate features 16 dims), Appendix J.

File format (``Protocol/subjectNNN.dat``, subjects 101-109)
------------------------------------------------------------
Space-separated text, one row per 10 ms (IMUs at 100 Hz), 54 columns, missing values written ``NaN``:

=========  ==========================================================================================
column     content
=========  ==========================================================================================
1          timestamp (s)
2          activity id (0 = transient, see :data:`ACTIVITY_NAMES`)
3          heart rate (bpm), ~9 Hz: a value on about 9 rows in 100, ``NaN`` elsewhere
4-20       IMU hand  (17 channels, :data:`IMU_CHANNELS`)
21-37      IMU chest
38-54      IMU ankle
=========  ==========================================================================================

Each IMU block: temperature (C), acc +-16 g x/y/z (m/s^2), acc +-6 g x/y/z (m/s^2), gyro x/y/z (rad/s),
magnetometer x/y/z (uT), orientation w/x/y/z (documented as invalid in this collection).

Public API
----------
- :func:`load_pamap2_subject` / :func:`load_pamap2_protocol`: parse files into :class:`Pamap2Recording`
  (:mod:`freamer_rl.data.pamap2_parse`: streamed in blocks of lines through numpy's C text reader with vectorised
  value checks, in memory proportional to the float64 output, not to the text). A malformed file raises
  :class:`Pamap2FormatError` with one line naming the file, the 1-based line and, where relevant, the 1-based
  column.
- :func:`pamap2_features`: the paper's observation at a chosen step rate (default 1 Hz) ->
  :class:`Pamap2Features` with ``imu`` ``[N, 36]`` and ``hr_features`` ``[N, 16]``
  (:mod:`freamer_rl.data.pamap2_observation`).
- :func:`synthetic_recording` / :func:`write_synthetic_pamap2`: synthetic subjects with plausible statistics,
  written in exactly the file format above (the dataset cannot be downloaded here; the synthetic data is the
  embedded default and the test data; the real dataset is read when a folder is given)
  (:mod:`freamer_rl.data.pamap2_synthetic`).

Constants, tables, the error type and the containers live in :mod:`freamer_rl.data.pamap2_format`; this package's
face lists the public names once (``from freamer_rl.data import load_pamap2_subject``).

IMU features (36 = 3 sites x 12), order ``hand, chest, ankle``; inside a site the file order without temperature
and orientation: ``acc16 x,y,z | acc6 x,y,z | gyro x,y,z | mag x,y,z``. Scaling: accelerations in g
(m/s^2 / 9.80665; typically [-3, 3], saturating at +-16 / +-6), gyro in rad/s (typically [-10, 10]),
magnetometer in units of 50 uT (typically [-2, 2]). See :data:`IMU_FEATURE_NAMES`.

Heart-rate features (16), see :data:`HR_FEATURE_NAMES` and :func:`pamap2_features` for the table.
"""

from __future__ import annotations

from freamer_rl.data import pamap2_format
from freamer_rl.data.pamap2_format import *  # noqa: F403  (its public names, listed once in its __all__)
from freamer_rl.data.pamap2_observation import hr_feature_sequence, pamap2_features
from freamer_rl.data.pamap2_parse import load_pamap2_protocol, load_pamap2_subject
from freamer_rl.data.pamap2_synthetic import synthetic_recording, write_synthetic_pamap2

__all__ = [
    *pamap2_format.__all__,
    "hr_feature_sequence",
    "load_pamap2_protocol",
    "load_pamap2_subject",
    "pamap2_features",
    "synthetic_recording",
    "write_synthetic_pamap2",
]
