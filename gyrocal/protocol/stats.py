"""Counters shared by the serial and CAN decoders, so a driver reports both links the same way."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class DecoderStats:
    """What a decoder saw. Every rejected frame is counted somewhere, never silently lost.

    frames: messages yielded (serial) or CAN frames accepted (CAN); bytes: bytes fed in.
    crc_errors: frames (or CAN coefficient commits) whose CRC failed.
    resyncs: times the decoder gave up a candidate frame or partial sample and hunted again.
    oversize: serial length fields above the payload cap.
    length_errors: a length (or CAN DLC) that does not fit the message type's layout.
    garbage_bytes: bytes skipped while hunting for a sync word (serial) or in unknown frames (CAN).
    seq_gaps: SAMPLE seq not one more than the previous (u32 wrap allowed); lost_samples sums them.
    unknown_types: frames with a valid CRC but a type (or CAN id) this decoder does not know.
    incomplete: CAN samples or coefficient transfers abandoned with a missing or duplicated part.
    unanchored: CAN samples dropped because no SAMPLE_TIME anchor had given the unit time yet.
    foreign_frames: CAN frames of other nodes or other protocols on a shared bus (ignored, not errors).
    bad_values: coefficient sets under a valid CRC that hold NaN or Inf (dropped).
    implausible: CAN samples whose time does not follow from their sequence number (dropped).
    repeated: samples whose seq is the previous sample's, with the same values (a bus logged twice, a
        gateway that sends a frame again): dropped, since a copy believed weighs its sample twice.
    conflicting: the same, with other values: another sender on the unit's ids. The copy that came
        second is dropped; which one is the unit's cannot be told (an outside user's CAN log whose
        forged copies came first: x constant +180 deg/h where the truth was -180, with a count).
    """

    frames: int = 0
    bytes: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    oversize: int = 0
    length_errors: int = 0
    garbage_bytes: int = 0
    seq_gaps: int = 0
    lost_samples: int = 0
    unknown_types: int = 0
    incomplete: int = 0
    unanchored: int = 0
    foreign_frames: int = 0
    bad_values: int = 0
    implausible: int = 0
    repeated: int = 0
    conflicting: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict for JSON status output."""
        return asdict(self)

    def errors(self) -> int:
        """All rejected frames and parts (excludes gaps, which the link may cause without corruption)."""
        return (self.crc_errors + self.oversize + self.length_errors + self.unknown_types + self.incomplete
                + self.bad_values + self.implausible + self.repeated
                + self.conflicting)
