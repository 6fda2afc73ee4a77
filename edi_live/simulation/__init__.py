"""The DAVIS simulator: one scene generator shared by the tests, the benchmarks (tools/simulate.py is its
command line) and the USB emulator's generated scene. It is the ground truth, so it imports no EDI code.

Modules, each owning one part:
- config.py: `SceneConfig`, the named presets, validation.
- texture.py: the textures the scene is made of.
- motion.py: the moving scene (affine motion, a flickering lamp) and the render time grid.
- camera.py: the camera model (thresholds, APS response) and the realistic effects with their sources.
- events.py: the event model (ESIM crossings, refractory period, background, shot noise, hot pixels).
- engine.py: `simulate()` and its result `Simulation`.
- output.py: AEDAT4 recording and ground-truth .npz files.
- stream.py: an endless scene as time-ordered packets, for the emulator.
- colour_scene.py: colour scenes (SceneConfig.color_filter): a BGR texture seen through a Bayer mosaic.
"""

from edi_live.simulation.camera import EFFECTS, linearise_aps, preset, true_camera, with_effects
from edi_live.simulation.colour_scene import DAVIS346_COLOR_FILTER, make_colour_texture
from edi_live.simulation.config import PRESETS, RESOLUTIONS, SceneConfig
from edi_live.simulation.engine import Simulation, simulate
from edi_live.simulation.output import load_ground_truth, save_ground_truth, write_aedat4
from edi_live.simulation.texture import PROCEDURAL_TEXTURES, SKIMAGE_TEXTURES, make_texture

__all__ = ["DAVIS346_COLOR_FILTER", "EFFECTS", "PRESETS", "PROCEDURAL_TEXTURES", "RESOLUTIONS", "SKIMAGE_TEXTURES", "SceneConfig",
           "Simulation", "linearise_aps", "load_ground_truth", "make_colour_texture", "make_texture", "preset", "save_ground_truth",
           "simulate", "true_camera", "with_effects", "write_aedat4"]
