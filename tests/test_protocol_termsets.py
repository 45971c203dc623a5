"""Term-set ids: stable 16-bit hashes of the canonical names, and a registry the unit can hold."""

from __future__ import annotations

import binascii

import pytest

from gyrocal.errors import ProtocolError
from gyrocal.model.terms import SEED000_TERMS
from gyrocal.protocol import termsets


def test_terms_id_is_crc16_ccitt_false_of_the_comma_joined_names() -> None:
    assert binascii.crc_hqx(b"123456789", 0xFFFF) == 0x29B1  # CRC-16/CCITT-FALSE check value
    assert termsets.terms_id(SEED000_TERMS) == binascii.crc_hqx(",".join(SEED000_TERMS).encode(), 0xFFFF)
    assert termsets.SEED000_ID == 0xF2FF and termsets.EXTENDED_TEMP_ID == 0x549E  # documented values


def test_spaces_do_not_change_the_id_but_order_does() -> None:
    assert termsets.terms_id(["1", "gx * gy"]) == termsets.terms_id(["1", "gx*gy"])
    assert termsets.terms_id(["1", "gx"]) != termsets.terms_id(["gx", "1"])


def test_known_sets_resolve_to_their_names() -> None:
    assert termsets.names_for(termsets.SEED000_ID) == SEED000_TERMS
    assert termsets.names_for(termsets.EXTENDED_TEMP_ID)[-4:] == ("temp", "temp^2", "dtemp", "temp*dtemp")
    assert termsets.names_for(0x0000 if termsets.SEED000_ID else 1) is None


def test_register_adds_a_set_and_rejects_bad_names() -> None:
    tid = termsets.register(["1", "gx", "exp(-t_on/300)"])
    assert termsets.names_for(tid) == ("1", "gx", "exp(-t_on/300)")
    assert termsets.register(["1", "gx", "exp(-t_on/300)"]) == tid  # idempotent
    for bad in ([], ["a,b"], [""], ["temp°"]):
        with pytest.raises(ProtocolError):
            termsets.terms_id(bad)
