"""Controller profiles with a force set-point, for force and load channels on twins.

The lab's Modbus map of ``examples/controllers/modbus_map.toml`` with a force set-point role
(``roles.force_setpoint``, docs/profiles.md): the map a force-controlled channel's driver
writes and its twin decodes.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MODBUS_MAP = ROOT / "examples" / "controllers" / "modbus_map.toml"

#: a force set-point register pair, float32 in kN, beside the map's displacement set-point
FORCE_ROLE = """
[roles.force_setpoint]
table = "holding"
address = 104
type = "float32"
units = "kN"
"""


def force_map(directory: Path) -> Path:
    """Write the Modbus map with a force set-point into ``directory``; its path."""
    text = MODBUS_MAP.read_text()
    if "force_setpoint" not in text:
        text += FORCE_ROLE
    p = Path(directory) / "force_map.toml"
    p.write_text(text)
    return p
