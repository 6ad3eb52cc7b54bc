"""Data: the synthetic egocentric stereo clip engine (the clip-folder format itself is
`esther_jax.clips`).

Public names: `SynthConfig`, `make_clip`, `write_clip`, `load_clip`, `synthesize`
(motion, detector simulation, rendering, crops, flow tokens).
"""

from .synth import Clip as Clip
from .synth import SynthConfig as SynthConfig
from .synth import load_clip as load_clip
from .synth import make_clip as make_clip
from .synth import synthesize as synthesize
from .synth import write_clip as write_clip
