"""ATI Net F/T raw data transfer (RDT) over UDP: the wire format, per ATI's Net F/T manual.

Request (8 bytes, big-endian): uint16 header 0x1234, uint16 command, uint32 sample count
(0 = stream until told to stop). Commands: 0x0000 stop, 0x0002 start real-time streaming,
0x0003 start buffered streaming, 0x0042 set software bias.

Record (36 bytes, big-endian): uint32 rdt_sequence (per UDP packet), uint32 ft_sequence (per
internal sample), uint32 status (0 = healthy), then int32 Fx Fy Fz Tx Ty Tz in counts. Force =
counts / counts_per_force, torque = counts / counts_per_torque, in the units the box is set to
(its web page's netftapi2.xml: cfgcpf, cfgcpt, scfgfu, scfgtu).
"""

from __future__ import annotations

import struct

PORT = 49152
HEADER = 0x1234
CMD_STOP = 0x0000
CMD_START_REALTIME = 0x0002
REQUEST = struct.Struct(">HHI")
RECORD = struct.Struct(">IIIiiiiii")

#: Unit strings of netftapi2.xml -> factor to SI (N, N m).
FORCE_UNITS = {"N": 1.0, "kN": 1e3, "lbf": 4.4482216152605, "klbf": 4448.2216152605, "g": 9.80665e-3, "kg": 9.80665}
TORQUE_UNITS = {"Nm": 1.0, "N-m": 1.0, "Nmm": 1e-3, "N-mm": 1e-3, "kNm": 1e3, "kN-m": 1e3, "lbf-in": 0.112984829027617,
                "lbfin": 0.112984829027617, "lbf-ft": 1.3558179483314, "lbfft": 1.3558179483314}


def request(command: int, count: int = 0) -> bytes:
    """An 8-byte RDT request."""
    return REQUEST.pack(HEADER, command, count)


def parse_record(data: bytes) -> tuple[int, int, int, tuple[int, ...]]:
    """(rdt_sequence, ft_sequence, status, counts (6,)) of one record; ValueError on a wrong size."""
    if len(data) != RECORD.size:
        raise ValueError(f"an RDT record has {RECORD.size} bytes, got {len(data)}")
    v = RECORD.unpack(data)
    return v[0], v[1], v[2], tuple(v[3:])
