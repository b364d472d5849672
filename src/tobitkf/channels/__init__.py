"""What happens between the sensor and the estimator, as small composable pieces.

One description of a channel serves both the simulator (which draws it) and the
estimator (which knows its statistics). Core piece: :class:`Censoring`.
Channel modules of the other estimator families live beside it
(``fading.py``, ``protocol.py``, ...).
"""

from .censoring import Censoring, multi_region

__all__ = ["Censoring", "multi_region"]
