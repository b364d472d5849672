"""What happens between the sensor and the estimator, as small composable pieces.

One description of a channel serves both the simulator (which draws it) and the estimator (which
knows its statistics): every piece implements :class:`~tobitkf.channels.base.Channel`
(:mod:`tobitkf.channels.base`). Pieces: :class:`Censoring` (Tobit limits, :mod:`.censoring`),
:class:`~tobitkf.channels.fading.RiceFading` (:mod:`.fading`),
:class:`~tobitkf.channels.protocol.ProtocolChannel` (:mod:`.protocol`),
:class:`~tobitkf.channels.saturation.RandomSaturation` (:mod:`.saturation`),
:class:`~tobitkf.channels.quantizer.Quantizer` (:mod:`.quantizer`), and the coefficient laws of :mod:`.laws`.
A channel's compiled update (its ``compiled_block``) may call the helpers of :mod:`.compiled` (which imports numba,
so it is not imported here). The names of ``__all__`` are the package's top-level channel names too.
"""

from .base import Channel
from .censoring import Censoring, multi_region
from .quantizer import Quantizer

__all__ = ["Channel", "Censoring", "multi_region", "Quantizer"]
