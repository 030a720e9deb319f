"""Codec tests: documented examples, input split at every byte offset, fuzzing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uwb_env.hardware import tlv
from uwb_env.hardware.errors import ParseError
from uwb_env.hardware.pans_shell import (
    AnchorRange,
    GenericModeError,
    LocationReport,
    Prompt,
    ShellDecoder,
    TextLine,
    format_lec,
    parse_lec,
    parse_lep,
    parse_les,
)
from uwb_env.hardware.tiers import (
    Banner,
    RangeMatrixMessage,
    RejectedMatrix,
    RoleSwap,
    TiersDecoder,
    WaitingForStart,
    encode_matrix,
    parse_row,
)

# -- TIERS -----------------------------------------------------------------------------------------
ROUND = (b"Singled Sided Two Way Ranging INIT\r\n"
         b"responder becomes initiator and viceversa\r\n"
         b"0 , 0 , 0 , 0 , 1 , 144 , 0 , 2 , 1 , 244 , 0 , 3 , 1 , 44 , 0 , 1 , \r\n"
         b" 1 , 145 , 0 , 2 , 0 , 0 , 0 , 0 , 1 , 45 , 0 , 2 , 1 , 243 , 0 , 4 , \r\n"
         b" 1 , 245 , 0 , 1 , 1 , 46 , 0 , 3 , 0 , 0 , 0 , 0 , 1 , 144 , 0 , 2 , \r\n"
         b" 1 , 45 , 0 , 2 , 1 , 242 , 0 , 1 , 1 , 145 , 0 , 3 , 0 , 0 , 0 , 0 , \r\n"
         b" \r\n Waiting for Start order\r\n")


def _kinds(messages):
    return [type(m).__name__ for m in messages]


def test_tiers_documented_round_decodes_to_centimetre_matrix():
    msgs = TiersDecoder().feed(ROUND)
    assert _kinds(msgs) == ["Banner", "RoleSwap", "RangeMatrixMessage", "WaitingForStart"]
    m = msgs[2]
    assert m.mean_m[0, 1] == pytest.approx(4.00) and m.std_m[0, 1] == pytest.approx(0.02)  # 1*256+144 cm
    assert m.mean_m[1, 0] == pytest.approx(4.01) and m.mean_m[0, 2] == pytest.approx(5.00)
    assert np.all(np.diag(m.mean_m) == 0)


def test_tiers_input_split_at_every_offset_gives_the_same_messages():
    whole = TiersDecoder().feed(ROUND)
    for cut in range(len(ROUND) + 1):
        dec = TiersDecoder()
        assert dec.feed(ROUND[:cut]) + dec.feed(ROUND[cut:]) == whole


def test_tiers_truncated_row_is_rejected_not_misread():
    lines = ROUND.split(b"\r\n")
    lines[3] = lines[3][:30]  # TX-FIFO overflow cut row 2
    msgs = TiersDecoder().feed(b"\r\n".join(lines))
    assert "RangeMatrixMessage" not in _kinds(msgs)
    assert any(isinstance(m, RejectedMatrix) for m in msgs)
    # a row interrupted by a banner (device reset mid-print) is rejected too
    msgs = TiersDecoder().feed(ROUND.split(b"\r\n", 3)[2] + b"\r\nSingled Sided Two Way Ranging INIT\r\n")
    assert isinstance(msgs[0], RejectedMatrix) and isinstance(msgs[1], Banner)


def test_tiers_encoder_roundtrip_truncates_to_centimetres():
    rng = np.random.default_rng(0)
    mean = rng.uniform(0.5, 30, (4, 4))
    std = rng.uniform(0, 0.2, (4, 4))
    (m, w) = TiersDecoder().feed(encode_matrix(mean, std))
    assert isinstance(w, WaitingForStart)
    off = ~np.eye(4, dtype=bool)
    assert np.all((mean - m.mean_m)[off] >= -1e-9) and np.all((mean - m.mean_m)[off] < 0.01 + 1e-9)
    assert np.all(np.abs(std - m.std_m)[off] < 0.01 + 1e-9)


def test_tiers_row_parser_errors():
    with pytest.raises(ParseError, match="16 comma"):
        parse_row("1 , 2 , 3 , ")
    with pytest.raises(ParseError, match="above 255"):
        parse_row(" , ".join(["300"] * 16) + " , ")


# -- PANS shell ------------------------------------------------------------------------------------
LEC = ("DIST,4,AN0,1151,5.00,8.00,2.25,6.44,AN1,0CA8,0.00,8.00,2.25,6.50,AN2,111C,5.00,0.00,2.25,3.24,"
       "AN3,1150,0.00,0.00,2.25,3.19,POS,2.55,2.01,1.71,98")
LES = ("1151[5.00,8.00,2.25]=6.48 0CA8[0.00,8.00,2.25]=6.51 111C[5.00,0.00,2.25]=3.18 "
       "1150[0.00,0.00,2.25]=3.16 le_us=2576 est[2.57,1.98,1.68,100]")


def test_documented_lec_les_lep_lines():
    r = parse_lec(LEC)
    assert [a.anchor_id for a in r.ranges] == ["1151", "0CA8", "111C", "1150"]
    assert r.ranges[1] == AnchorRange("0CA8", (0.0, 8.0, 2.25), 6.50)
    assert r.position_m == (2.55, 2.01, 1.71) and r.quality == 98
    s = parse_les(LES)
    assert s.ranges[3].distance_m == 3.16 and s.position_m == (2.57, 1.98, 1.68) and s.quality == 100
    p = parse_lep("POS,2.57,2.00,1.67,97")
    assert p.position_m == (2.57, 2.0, 1.67) and p.quality == 97 and p.ranges == ()
    assert parse_lec(format_lec(list(r.ranges), r.position_m, r.quality)) == r


def test_corrupted_lec_keeps_valid_groups_and_drops_duplicates():
    bad = ("DIST,4,AN0,0090,0.00,0.00,0.00,3.25,AN1,D91E,0.00,0.00,0.00,3.33,AN2,0487,0.00,0.00,0.00,0.18,"
           "AN3,15BA,0.00,0,AN3,15BA,0.00,0.00,0.00,0.00")
    r = parse_lec(bad)
    assert [a.anchor_id for a in r.ranges] == ["0090", "D91E", "0487", "15BA"]
    assert r.ranges[3].distance_m == 0.0 and r.position_m is None
    with pytest.raises(ParseError):
        parse_lec("DIST,2,AN0,12")


def test_shell_stream_with_echo_glued_prompt_and_generic_error():
    stream = (b"@\x01\x01" + b"\r\n DWM1001 TWR Real Time Location System\r\n\r\ndwm> lec\r\ndwm> " + LEC.encode()
              + b"\r\n" + LEC.encode() + b"\r\n")
    whole = ShellDecoder().feed(stream)
    kinds = _kinds(whole)
    assert kinds[0] == "GenericModeError" and kinds.count("LocationReport") == 2 and "Prompt" in kinds
    assert all(isinstance(m, (GenericModeError, TextLine, Prompt, LocationReport)) for m in whole)
    for cut in range(len(stream) + 1):
        dec = ShellDecoder()
        assert dec.feed(stream[:cut]) + dec.feed(stream[cut:]) == whole


# -- TLV -------------------------------------------------------------------------------------------
def test_documented_loc_get_example_prefix_and_roundtrip():
    pos = tlv.Position.unpack(bytes.fromhex("4b0a00001f0400009c0e000064"))
    assert (pos.x_m, pos.y_m, pos.z_m, pos.quality) == (2.635, 1.055, 3.74, 100)
    anchors = [tlv.Distance(0x1150 + i, 3.0 + i, 100, tlv.Position(i, 2 * i, 2.25, 100)) for i in range(4)]
    frame = tlv.encode_location_tag(pos, anchors)
    assert frame[:21] == bytes.fromhex("400100410d4b0a00001f0400009c0e0000644951") + bytes([4])
    loc = tlv.decode_location(tlv.parse_response(frame))
    assert loc.node == "tag" and loc.position == pos and loc.distances == tuple(anchors)
    anchor_frame = tlv.encode_location_anchor(pos, [tlv.Distance(0xDECA000000001151, 6.48, 90)])
    loc = tlv.decode_location(tlv.parse_response(anchor_frame))
    assert loc.node == "anchor" and loc.distances[0].address == 0xDECA000000001151


def test_tlv_other_responses_and_errors():
    cfg = tlv.decode_cfg(tlv.parse_response(bytes.fromhex("400100460252 20".replace(" ", ""))))
    assert cfg["mode"] == "anchor" and cfg["loc_engine"] and cfg["uwb_mode"] == "active"
    assert tlv.decode_update_rate(tlv.parse_response(bytes.fromhex("4001004504010005 00".replace(" ", "")))) == (1, 5)
    assert tlv.parse_response(b"\x40\x01\x01").error == 1
    with pytest.raises(ParseError, match="error 1"):
        tlv.decode_position(tlv.parse_response(b"\x40\x01\x01"))
    with pytest.raises(ParseError, match="shorter than its length"):
        tlv.parse_response(b"\x40\x01\x00\x41\x0d\x00")
    assert tlv.response_length(b"\x40\x01\x00\x41\x0d\x00") is None
    assert tlv.response_length(b"\x40\x01\x00\x45\x04\x01\x00\x05\x00\x40") == 9


# -- fuzzing: only the documented error escapes ----------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400), st.integers(0, 400))
def test_decoders_never_raise_on_garbage(data, cut):
    for dec in (TiersDecoder(), ShellDecoder()):
        dec.feed(data[:cut])
        dec.feed(data[cut:])


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=120))
def test_parsers_raise_only_parse_error(data):
    text = data.decode("latin-1")
    for parse in (parse_lec, parse_les, parse_lep, parse_row):
        try:
            parse(text)
        except ParseError:
            pass
    for parse in (tlv.parse_response, lambda b: tlv.decode_location(tlv.parse_response(b)),
                  lambda b: tlv.decode_cfg(tlv.parse_response(b)), tlv.response_length, tlv.Position.unpack):
        try:
            parse(data)
        except ParseError:
            pass


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 0xFFFF), st.floats(0, 100), st.integers(0, 100)), max_size=12),
       st.binary(max_size=8))
def test_tlv_location_fuzz_with_mutations(items, noise):
    dists = [tlv.Distance(a, round(d, 3), q, tlv.Position(1.0, 2.0, 3.0, 50)) for a, d, q in items]
    frame = tlv.encode_location_tag(tlv.Position(0.1, 0.2, 0.3, 99), dists)
    assert tlv.decode_location(tlv.parse_response(frame)).distances == tuple(dists)
    try:
        tlv.decode_location(tlv.parse_response(frame[: len(frame) // 2] + noise))
    except ParseError:
        pass


def test_other_messages_are_typed():
    msgs = TiersDecoder().feed(b"hello\r\nresponder becomes initiator and viceversa\r\n")
    assert isinstance(msgs[1], RoleSwap) and msgs[0].text == "hello"
    assert RangeMatrixMessage(np.zeros((4, 4)), np.zeros((4, 4))) != RejectedMatrix("x")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-99, 99), st.floats(-99, 99), st.floats(-9, 9), st.floats(0, 99)),
                min_size=1, max_size=4),
       st.booleans())
def test_lec_fast_path_agrees_with_the_group_parser(values, with_pos):
    from uwb_env.hardware.pans_shell import _lec_by_groups, _lec_fast

    ranges = [AnchorRange(f"{0x1150 + i:04X}", (round(x, 2), round(y, 2), round(z, 2)), round(d, 2))
              for i, (x, y, z, d) in enumerate(values)]
    line = format_lec(ranges, (1.0, -2.0, 0.5) if with_pos else None, 77 if with_pos else None)
    fast = _lec_fast(line)
    assert fast is not None and fast == _lec_by_groups(line, line)
    assert [r.anchor_id for r in fast.ranges] == [r.anchor_id for r in ranges]


def test_lec_anchor_cache_reuses_positions_but_never_distances():
    from uwb_env.hardware import pans_shell

    a = parse_lec("DIST,2,AN0,1151,5.00,8.00,2.25,6.44,AN1,0CA8,0.00,8.00,2.25,6.50,POS,1.00,2.00,0.50,90")
    b = parse_lec("DIST,2,AN0,1151,5.00,8.00,2.25,1.11,AN1,0CA8,0.00,8.00,2.25,2.22,POS,3.00,4.00,0.50,80")
    assert [r.distance_m for r in a.ranges] == [6.44, 6.50] and [r.distance_m for r in b.ranges] == [1.11, 2.22]
    assert a.ranges[0].position_m == b.ranges[0].position_m == (5.0, 8.0, 2.25)
    assert b.position_m == (3.0, 4.0, 0.5) and b.quality == 80
    # the cache stays bounded and correct when a stream keeps bringing new anchor groups
    for k in range(pans_shell._ANCHOR_CACHE_SIZE + 10):
        r = parse_lec(f"DIST,1,AN0,1151,{k}.00,0.00,0.00,1.50")
        assert r.ranges[0].position_m == (float(k), 0.0, 0.0)
    assert len(pans_shell._ANCHOR_CACHE) <= pans_shell._ANCHOR_CACHE_SIZE
