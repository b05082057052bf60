"""Procedural dynamic RGB-D scenes with exact ground truth (the synthetic scene family).

``SyntheticSequence(scene=<preset>)`` is the dataset; presets live in :mod:`.presets`. Layers, bottom
up: :mod:`.textures`, :mod:`.shapes`, :mod:`.motion` -> :mod:`.scene` -> :mod:`.layout`,
:mod:`.render`, :mod:`.sensor`, :mod:`.cache` -> :mod:`.presets` -> :mod:`.sequence`.
"""

from data_modules.synthetic.presets import PRESETS
from data_modules.synthetic.sensor import SensorModel
from data_modules.synthetic.sequence import SyntheticSequence

__all__ = ["PRESETS", "SensorModel", "SyntheticSequence"]
