"""BioTac over SPI: command bytes, words and frames, the simulator's error words, the reader under faults,
the TCP bridge, and the Cheetah transport (missing vendor library; queue mapping on a stand-in module)."""

import socket
import sys
import types
from collections.abc import Sequence

import numpy as np
import pytest

from hardware.biotac.bridge import MAGIC, SpiBridgeServer, decode_ops, encode_ops
from hardware.biotac.client import BioTacError, BioTacReader
from hardware.biotac.protocol import (
    COMMAND_DELAY_NS,
    ELECTRODE_CHANNELS,
    FRAME_CHANNELS,
    FRAME_LENGTH,
    READ_COMMAND,
    Channel,
    Delay,
    ErrorWord,
    Property,
    Select,
    SpiOp,
    Transfer,
    TransportError,
    WordError,
    decode_word,
    encode_word,
    frame_ops,
    odd_parity_ok,
    sample_command,
)
from hardware.biotac.sim import SimBioTac, SimBioTacBus
from hardware.biotac.transport import CHEETAH_PATH_ENV, CheetahTransport, open_transport
from hardware.stamped import wait_for

ELECTRODES = np.arange(19) * 150 + 400
PDC = 1717


def _bus(**sensors: SimBioTac) -> SimBioTacBus:
    return SimBioTacBus({int(slot[1:]): s for slot, s in sensors.items()} or {1: SimBioTac(lambda: (ELECTRODES, PDC))})


def test_command_bytes_match_the_manual() -> None:
    table = "A2 A4 A7 A8 AB AD AE B0 B3 B5 B6 B9 BA BC BF C1 C2 C4 C7".split()
    assert [sample_command(ch) for ch in ELECTRODE_CHANNELS] == [int(b, 16) for b in table]
    assert [sample_command(ch) for ch in (Channel.PAC, Channel.PDC, Channel.TAC, Channel.TDC, Channel.HAL)] == [
        0x80,
        0x83,
        0x85,
        0x86,
        0x9E,
    ]
    assert all(odd_parity_ok(p) for p in Property) and odd_parity_ok(READ_COMMAND)


def test_words_round_trip_and_every_bad_word_is_caught() -> None:
    for value in range(4096):
        b0, b1 = encode_word(value)
        assert odd_parity_ok(b0) and odd_parity_ok(b1)
        assert decode_word(b0, b1) == value
        for bit in range(16):  # any single flipped bit fails a parity check
            flipped = (b0 << 8 | b1) ^ (1 << bit)
            try:
                decode_word(flipped >> 8, flipped & 0xFF)
            except WordError:
                continue
            pytest.fail(f"bit {bit} flipped in the word of {value} went unnoticed")
    for error in ErrorWord:
        with pytest.raises(WordError) as info:
            decode_word(error >> 8, error & 0xFF)
        assert info.value.error is error


def test_frame_schedule_and_timing() -> None:
    assert FRAME_LENGTH == 44
    assert FRAME_CHANNELS[:4] == (17, Channel.PAC, 18, Channel.PAC)
    assert FRAME_CHANNELS[-6:] == (Channel.PDC, Channel.PAC, Channel.TAC, Channel.PAC, Channel.TDC, Channel.PAC)
    ops = frame_ops(0x01)
    busy_ns = sum(op.ns for op in ops if isinstance(op, Delay))
    busy_ns += sum(len(op.data) for op in ops if isinstance(op, Transfer)) * 8e6 / 4400
    assert busy_ns == pytest.approx(1e9 / 100, rel=1e-3)  # 44 samples at 4400 samples/s -> 100 Hz


def _sample(bus: SimBioTacBus, command: int, delay_ns: int = COMMAND_DELAY_NS) -> bytes:
    ops: list[SpiOp] = [Select(1), Transfer(bytes([command, 0])), Select(0), Delay(delay_ns)]
    ops += [Select(1), Transfer(b"\x00\x00"), Select(0), Delay(300_000)]
    return bus.batch(ops)[2:]


def test_simulated_sensor_answers_error_words_like_the_real_one() -> None:
    bus = _bus()
    assert decode_word(*_sample(bus, sample_command(Channel.PDC))) == PDC
    assert _sample(bus, 0x82) == ErrorWord.PARITY.to_bytes(2, "big")  # even parity
    assert _sample(bus, 0x01) == ErrorWord.UNKNOWN_COMMAND.to_bytes(2, "big")
    assert _sample(bus, sample_command(5)) == ErrorWord.CHANNEL_NOT_RECOGNISED.to_bytes(2, "big")
    assert _sample(bus, sample_command(17), delay_ns=10_000) == ErrorWord.INSUFFICIENT_DELAY.to_bytes(2, "big")
    ops = [Select(1), Transfer(bytes([sample_command(17), 0])), Select(0), Delay(COMMAND_DELAY_NS)] * 2
    ops += [Select(1), Transfer(b"\x00\x00"), Select(0)]
    assert bus.batch(ops)[-2:] == ErrorWord.INSUFFICIENT_SAMPLING_DELAY.to_bytes(2, "big")


def test_reader_identifies_and_samples_several_sensors() -> None:
    bus = _bus(s1=SimBioTac(lambda: (ELECTRODES, PDC)), s3=SimBioTac(lambda: (ELECTRODES[::-1], 5), serial="BT-THREE"))
    reader = BioTacReader(lambda: bus, 0x05)
    try:
        assert reader.info[1].serial == "BT-SIM-0000001" and reader.info[3].serial == "BT-THREE"
        assert reader.info[1].firmware == (2, 1, 0, 7)
        one, three = reader.frames[1].wait(1.0), reader.frames[3].wait(1.0)
        np.testing.assert_array_equal(one.electrodes, ELECTRODES)
        np.testing.assert_array_equal(three.electrodes, ELECTRODES[::-1])
        assert (one.pdc, three.pdc, one.pac.shape, one.tdc) == (PDC, 5, (22,), 2300)
        n = reader.stats["frames"]
        assert wait_for(lambda: reader.stats["frames"] >= n + 20, 2.0)  # 2 x 100 Hz; slack for load
        assert set(reader.stats) == {"frames"}  # the driver's timing never upsets the sensor
    finally:
        reader.close()


def test_missing_sensor_is_reported() -> None:
    with pytest.raises(BioTacError, match="no BioTac answers on slot 2"):
        BioTacReader(_bus, 0x02)


class _FlakyTransport:
    """Flips one MISO bit in every third batch (a noisy cable)."""

    def __init__(self, inner: SimBioTacBus) -> None:
        self.inner, self.calls = inner, 0

    def batch(self, ops: Sequence[SpiOp]) -> bytes:
        data = bytearray(self.inner.batch(ops))
        self.calls += 1
        if self.calls > 4 and self.calls % 3 == 0:  # leave the identification reads alone
            data[2 + 4 * (self.calls % FRAME_LENGTH) + self.calls % 2] ^= 0x10
        return bytes(data)

    def close(self) -> None:
        pass


def test_parity_errors_drop_frames_never_corrupt_them() -> None:
    flaky = _FlakyTransport(_bus())
    reader = BioTacReader(lambda: flaky, 0x01)
    seen: list[np.ndarray] = []
    try:
        assert wait_for(lambda: reader.stats["parity_errors"] >= 3, 10.0)
        for _ in range(10):
            seen.append(reader.frames[1].wait(1.0, after=reader.frames[1].count).electrodes)
    finally:
        reader.close()
    assert all(np.array_equal(e, ELECTRODES) for e in seen)
    assert set(reader.stats) == {"frames", "parity_errors"}
    assert reader.stats["frames"] >= 1.5 * reader.stats["parity_errors"]  # 2 good batches per bad one


def test_tcp_bridge_carries_batches_and_survives_disconnects_and_garbage() -> None:
    bridge = SpiBridgeServer(_bus())
    reader = BioTacReader(lambda: open_transport(f"tcp://127.0.0.1:{bridge.port}"), 0x01, reconnect_s=0.05)
    try:
        assert reader.frames[1].wait(1.0).pdc == PDC
        bridge.disconnect_all()
        assert wait_for(lambda: reader.stats["reconnects"] == 1, 10.0)
        n = reader.frames[1].count
        assert wait_for(lambda: reader.frames[1].count > n + 3, 10.0)
        with socket.create_connection(("127.0.0.1", bridge.port), timeout=1.0) as rogue:
            rogue.sendall(MAGIC + (3).to_bytes(4, "big") + b"Zzz")
            reply = rogue.recv(1024)
            assert reply[:4] == MAGIC and reply[8] == 1 and b"unknown op" in reply
        n = reader.frames[1].count
        assert wait_for(lambda: reader.frames[1].count > n + 3, 10.0)
    finally:
        reader.close()
        bridge.close()
    ops = [Select(1), Transfer(b"\x83\x00"), Delay(50_000)]
    assert decode_ops(encode_ops(ops)) == ops
    with pytest.raises(ValueError, match="truncated"):
        decode_ops(encode_ops(ops)[:-2])
    with pytest.raises(TransportError, match="cannot reach"):
        open_transport("tcp://127.0.0.1:1", timeout_s=0.2)
    with pytest.raises(ValueError, match="unknown BioTac transport"):
        open_transport("usb://0")


def test_cheetah_without_vendor_library_says_how_to_get_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "cheetah_py", None)  # makes the import fail
    with pytest.raises(TransportError, match="totalphase.com") as info:
        open_transport("cheetah")
    assert CHEETAH_PATH_ENV in str(info.value) and "cheetah_py" in str(info.value)


def _fake_cheetah(bus: SimBioTacBus) -> types.ModuleType:
    """A stand-in for the vendor's cheetah_py that replays the queued batch on a simulated bus."""
    mod = types.ModuleType("cheetah_py")
    mod.calls = []
    queue: list[SpiOp] = []
    for name in ("CH_SPI_POL_RISING_FALLING", "CH_SPI_PHASE_SAMPLE_SETUP", "CH_SPI_BITORDER_MSB"):
        setattr(mod, name, 0)
    mod.CH_TARGET_POWER_ON, mod.CH_TARGET_POWER_OFF = 3, 0

    def record(name: str, result: object = 0):
        def call(*args: object) -> object:
            mod.calls.append((name, args))
            return result(*args) if callable(result) else result

        return call

    mod.ch_open = record("open", 7)
    mod.ch_close = record("close")
    mod.ch_spi_configure = record("configure")
    mod.ch_spi_bitrate = record("bitrate", lambda h, khz: khz)
    mod.ch_target_power = record("power")
    mod.ch_sleep_ms = record("sleep")
    mod.ch_spi_queue_clear = record("clear", lambda h: queue.clear())
    mod.ch_spi_queue_oe = record("oe")
    mod.ch_spi_queue_ss = record("ss", lambda h, mask: queue.append(Select(mask)))
    mod.ch_spi_queue_array = record("array", lambda h, arr: queue.append(Transfer(bytes(arr))))
    mod.ch_spi_queue_delay_ns = record("delay", lambda h, ns: queue.append(Delay(ns)))
    mod.ch_spi_batch_shift = record("shift", lambda h, n: (n, list(bus.batch(queue))))
    return mod


def test_cheetah_transport_maps_batches_onto_the_vendor_queue(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _fake_cheetah(_bus())
    monkeypatch.setitem(sys.modules, "cheetah_py", fake)
    reader = BioTacReader(lambda: CheetahTransport(port=0, bitrate_khz=4400), 0x01)
    try:
        np.testing.assert_array_equal(reader.frames[1].wait(1.0).electrodes, ELECTRODES)
    finally:
        reader.close()
    names = [name for name, _ in fake.calls]
    assert names[:5] == ["open", "configure", "bitrate", "power", "sleep"]
    assert ("power", (7, fake.CH_TARGET_POWER_ON)) in fake.calls and ("sleep", (100,)) in fake.calls
    assert names[-2:] == ["power", "close"] and fake.calls[-2] == ("power", (7, fake.CH_TARGET_POWER_OFF))
    assert names.count("oe") == names.count("clear") == names.count("shift") > 3
