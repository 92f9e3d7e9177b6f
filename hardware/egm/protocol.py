"""EGM message classes built at import time from `egm.proto`, and joint-vector conversions.

No protoc is needed: a small reader for the proto2 subset that `egm.proto` uses (package, messages,
nested enums, optional/repeated fields, `[default = ...]`) turns the schema into a
`FileDescriptorProto`, and the installed protobuf runtime makes the classes from it.

Joint conventions: the twin uses (7,) radians in chain order 1-2-7-3-4-5-6; EGM carries axes 1-6 in
`joints` and axis 7 in `externalJoints[0]`, all in degrees.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message

SCHEMA_PATH = Path(__file__).with_name("egm.proto")
MAX_DATAGRAM_BYTES = 1400  # larger EGM datagrams are rejected as oversized (real ones are ~400 bytes)
CHAIN_TO_EGM_AXES = (0, 1, 3, 4, 5, 6)  # chain indices of ABB axes 1..6
CHAIN_AXIS7 = 2  # chain index of ABB axis 7 (EGM externalJoints[0])

_FDP = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _FDP.TYPE_DOUBLE,
    "float": _FDP.TYPE_FLOAT,
    "int32": _FDP.TYPE_INT32,
    "int64": _FDP.TYPE_INT64,
    "uint32": _FDP.TYPE_UINT32,
    "uint64": _FDP.TYPE_UINT64,
    "bool": _FDP.TYPE_BOOL,
    "string": _FDP.TYPE_STRING,
    "bytes": _FDP.TYPE_BYTES,
}
_LABELS = {"optional": _FDP.LABEL_OPTIONAL, "required": _FDP.LABEL_REQUIRED, "repeated": _FDP.LABEL_REPEATED}
_TOKEN = re.compile(r'\s+|//[^\n]*|/\*.*?\*/|(?P<tok>"[^"]*"|[A-Za-z_][\w.]*|-?\d+(?:\.\d*)?|[{}\[\]=;])', re.S)


class EgmMessageError(ValueError):
    """A datagram is not a usable EGM message (garbage, truncated, oversized or missing fields)."""


def _tokens(text: str) -> list[str]:
    out, pos = [], 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise SyntaxError(f"egm.proto: unexpected character {text[pos]!r} at offset {pos}")
        if m.group("tok"):
            out.append(m.group("tok"))
        pos = m.end()
    return out


class _ProtoReader:
    """Recursive-descent reader of the proto2 subset used by egm.proto."""

    def __init__(self, text: str, filename: str) -> None:
        self.toks = _tokens(text)
        self.i = 0
        self.file = descriptor_pb2.FileDescriptorProto(name=filename, syntax="proto2")

    def next(self, expect: str | None = None) -> str:
        if self.i >= len(self.toks):
            raise SyntaxError("egm.proto: unexpected end of file")
        tok = self.toks[self.i]
        self.i += 1
        if expect is not None and tok != expect:
            raise SyntaxError(f"egm.proto: expected {expect!r}, got {tok!r} (token {self.i})")
        return tok

    def read(self) -> descriptor_pb2.FileDescriptorProto:
        while self.i < len(self.toks):
            tok = self.next()
            if tok == "syntax":
                self.next("=")
                if self.next() != '"proto2"':
                    raise SyntaxError("egm.proto: only proto2 is supported")
                self.next(";")
            elif tok == "package":
                self.file.package = self.next()
                self.next(";")
            elif tok == "message":
                self.message(self.file.message_type.add())
            else:
                raise SyntaxError(f"egm.proto: unexpected {tok!r} at top level")
        return self.file

    def message(self, msg: descriptor_pb2.DescriptorProto) -> None:
        msg.name = self.next()
        self.next("{")
        while (tok := self.next()) != "}":
            if tok == "enum":
                self.enum(msg.enum_type.add())
            elif tok == "message":
                self.message(msg.nested_type.add())
            elif tok in _LABELS:
                self.field(msg.field.add(), tok)
            else:
                raise SyntaxError(f"egm.proto: unexpected {tok!r} in message {msg.name}")

    def enum(self, enum: descriptor_pb2.EnumDescriptorProto) -> None:
        enum.name = self.next()
        self.next("{")
        while (tok := self.next()) != "}":
            self.next("=")
            enum.value.add(name=tok, number=int(self.next()))
            self.next(";")
        if self.i < len(self.toks) and self.toks[self.i] == ";":
            self.i += 1

    def field(self, field: _FDP, label: str) -> None:
        type_name = self.next()
        field.label = _LABELS[label]
        if type_name in _SCALARS:
            field.type = _SCALARS[type_name]
        else:
            field.type_name = type_name  # message or enum, resolved by the descriptor pool
        field.name = self.next()
        self.next("=")
        field.number = int(self.next())
        if (tok := self.next()) == "[":
            if self.next() != "default":
                raise SyntaxError(f"egm.proto: only [default = ...] options are supported ({field.name})")
            self.next("=")
            field.default_value = self.next().strip('"')
            self.next("]")
            tok = self.next()
        if tok != ";":
            raise SyntaxError(f"egm.proto: expected ';' after field {field.name}, got {tok!r}")


def read_proto(text: str, filename: str = "egm.proto") -> descriptor_pb2.FileDescriptorProto:
    """Parse proto2 schema text (the subset egm.proto uses) into a FileDescriptorProto."""
    return _ProtoReader(text, filename).read()


_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(read_proto(SCHEMA_PATH.read_text()))


def message_class(name: str) -> type[Message]:
    """The generated class of message `name` in package abb.egm (e.g. "EgmRobot")."""
    return message_factory.GetMessageClass(_POOL.FindMessageTypeByName(f"abb.egm.{name}"))


EgmHeader = message_class("EgmHeader")
EgmRobot = message_class("EgmRobot")
EgmSensor = message_class("EgmSensor")


def parse_datagram(cls: type[Message], data: bytes) -> Message:
    """Decode one datagram as `cls`; raise EgmMessageError for oversized or undecodable bytes."""
    if len(data) > MAX_DATAGRAM_BYTES:
        raise EgmMessageError(f"oversized EGM datagram ({len(data)} > {MAX_DATAGRAM_BYTES} bytes)")
    msg = cls()
    try:
        msg.ParseFromString(data)
    except DecodeError as exc:
        raise EgmMessageError(f"undecodable {cls.DESCRIPTOR.name} datagram ({len(data)} bytes): {exc}") from exc
    return msg


def chain_to_egm(q_rad: np.ndarray) -> tuple[list[float], list[float]]:
    """(7,) chain-order radians -> (axes 1-6 in degrees, [axis 7 in degrees]) for EGM."""
    deg = np.degrees(np.asarray(q_rad, dtype=float))
    return [float(deg[i]) for i in CHAIN_TO_EGM_AXES], [float(deg[CHAIN_AXIS7])]


def egm_to_chain(joints_deg: list[float], external_deg: list[float]) -> np.ndarray:
    """EGM axes 1-6 and externalJoints (degrees) -> (7,) chain-order radians.

    Raises EgmMessageError unless there are 6 finite joints and at least one external joint (axis 7).
    """
    if len(joints_deg) != 6 or len(external_deg) < 1:
        counts = f"{len(joints_deg)} + {len(external_deg)}"
        raise EgmMessageError(f"expected 6 joints + axis 7 in externalJoints, got {counts}")
    q = np.empty(7)
    q[list(CHAIN_TO_EGM_AXES)] = joints_deg
    q[CHAIN_AXIS7] = external_deg[0]
    if not np.all(np.isfinite(q)):
        raise EgmMessageError("non-finite joint value in EGM message")
    return np.radians(q)


def set_joints(planned: Message, q_rad: np.ndarray) -> None:
    """Fill an EgmPlanned/EgmFeedBack `planned` with chain-order joints `q_rad` (rad -> EGM degrees)."""
    joints, external = chain_to_egm(q_rad)
    planned.joints.joints[:] = joints
    planned.externalJoints.joints[:] = external


def get_joints(planned: Message) -> np.ndarray:
    """Chain-order joints (rad) from an EgmPlanned/EgmFeedBack; EgmMessageError when absent or malformed."""
    return egm_to_chain(list(planned.joints.joints), list(planned.externalJoints.joints))


def seq_newer(seqno: int, last: int) -> int:
    """How many steps uint32 `seqno` is ahead of `last` (modulo 2**32); <= 0 for old or repeated numbers."""
    diff = (seqno - last) % (1 << 32)
    return diff if diff < (1 << 31) else diff - (1 << 32)
