"""What to design: the config (preset, TOML documents, overrides), the presets and the settings
of the stages that are not the scene.

``resolve`` layers a preset, TOML documents and overrides into one validated ``Config``;
``to_toml`` writes it back so that a run can be repeated exactly.
"""

from aperture_fab.config.config import SECTION_KEYS, Config, parse_toml, resolve
from aperture_fab.config.stages import FabricationSettings, PhotometrySettings, ValidationSettings
from aperture_fab.config.written import to_dict, to_toml

__all__ = ["SECTION_KEYS", "Config", "FabricationSettings", "PhotometrySettings",
           "ValidationSettings", "parse_toml", "resolve", "to_dict", "to_toml"]
