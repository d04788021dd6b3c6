"""semantic-companion: the onboard companion service (MAVLink, MQTT, camera, simulation, CLI)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("semantic-companion")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
