"""Imports every module that owns a config section, so that :func:`iscd.core.config.describe`
and :func:`iscd.core.config.check_sections` see them all, and the camera registry, whose
resolver checks ``[rig]``'s camera URLs when a config is loaded (:mod:`iscd.drivers.urls`).

The CLI sits above every layer, so it may import them; :mod:`iscd.core.config` sits below them
all and knows the section names only (:data:`iscd.core.config.SECTION_NAMES`). A missing owner
is an ImportError here, not a silently skipped table.
"""

from __future__ import annotations

from iscd.core import config as _config
from iscd.decode.comms.settings import ReceiverConfig
from iscd.decode.ranging.config import RangingSettings
from iscd.decode.stream import PipelineSettings
from iscd.drivers import urls as _camera_urls  # noqa: F401  (installs the [rig] resolver)
from iscd.drivers.board.settings import BoardSettings
from iscd.outputs.base import OutputConfig, RerunConfig
from iscd.recording.recorder import RecordSettings
from iscd.rig.acquisition import AcquisitionOptions
from iscd.service.daemon import DaemonSettings

OWNERS: dict[str, type] = {
    "daemon": DaemonSettings, "acquisition": AcquisitionOptions, "tracking": PipelineSettings,
    "receiver": ReceiverConfig, "ranging": RangingSettings, "output": OutputConfig,
    "rerun": RerunConfig, "board": BoardSettings, "record": RecordSettings,
}
"""Each section's owner (the same classes :func:`iscd.core.config.section_owners` returns
once this module is imported)."""

missing = set(_config.SECTION_NAMES) - set(_config.section_owners())
if missing:  # pragma: no cover - a section without an owner is a programming error
    raise ImportError(f"config sections without an owner: {', '.join(sorted(missing))}")
