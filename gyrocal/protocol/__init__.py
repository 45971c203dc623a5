"""The unit's wire protocol: messages, serial framing with CRC-32, and CAN frames from a DBC.

Pure code: no ports, no threads. Drivers feed received bytes or CAN frames to a decoder and send what
the encoders return. docs/protocol.md describes every frame byte by byte.
"""

from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffTransferFailed,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    Sample,
    coeff_set_crc,
)
from gyrocal.protocol.serial_framing import FrameDecoder, encode_frame
from gyrocal.protocol.stats import DecoderStats
from gyrocal.protocol.termsets import names_for, register, terms_id

__all__ = [
    "CoeffAck", "CoeffNak", "CoeffRead", "CoeffReport", "CoeffTransferFailed", "CoeffWrite", "DecoderStats",
    "HelloRequest",
    "FrameDecoder", "Hello", "NakReason", "Sample", "coeff_set_crc", "encode_frame", "names_for",
    "register", "terms_id",
]
