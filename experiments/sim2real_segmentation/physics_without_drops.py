"""Print a physics JSON (as `diagnose` fits it) with its ray-drop effects left out, so a
ray-drop model from elsewhere (the GAN's x_n) can take their place."""
import json
import sys

DROPS = {
    "range_dropout", "incidence_dropout", "material_dropout", "beam_dropout",
    "self_occlusion", "uniform_dropout", "intensity_dropout",
}
physics = json.load(open(sys.argv[1]))
print(json.dumps({k: v for k, v in physics.items() if k not in DROPS}, indent=2))
