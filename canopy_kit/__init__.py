"""canopy-kit: per-tree canopy volumes from mobile LiDAR drives through orchards.

Importing the package is cheap: heavy libraries (open3d, pycolmap, pyvista) are imported
inside the functions that need them.
"""

from canopy_kit.errors import (
    CanopyKitError,
    ConfigError,
    InputError,
    PluginError,
    ProcessingError,
)

__version__ = "0.1.0"

__all__ = [
    "CanopyKitError",
    "ConfigError",
    "InputError",
    "PluginError",
    "ProcessingError",
    "__version__",
]
