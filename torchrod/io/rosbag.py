"""Readings from ROS bags and estimates into them, without a ROS install (the optional ``rosbags`` package:
``pip install "torchrod[ros]"``).

Reading (:class:`BagSource`)
    Any bag ``rosbags`` opens: a ROS 1 ``.bag`` file, or a ROS 2 bag directory (SQLite3 or MCAP storage). The
    topic's messages are ``std_msgs/msg/Float64MultiArray`` holding 2G values, ``ux_1, uy_1, ..., ux_G, uy_G``
    [1/m] in the rod file's grating order, with NaN for both values of a missing grating. A reading's ``t`` is
    the bag's time stamp of the message [s] and its ``id`` the message's index in the topic (0-based). A message
    that cannot be used (another length, a half-missing grating, a value beyond the bounds) becomes an error
    answer in its place, as a bad line of a file does (:mod:`torchrod.io.reading`).

Writing (:class:`BagWriter`)
    A ROS 2 bag directory (SQLite3 storage), or a ROS 1 bag when the path ends in ``.bag``; standard messages only,
    all stamped with the reading's ``t``, one message per topic per reading, so that the topics stay aligned:

    * ``/torchrod/estimate`` (``std_msgs/msg/String``): the full JSON answer line (forces, standard deviations,
      ``status``, ``p_value``, ...), or the error line;
    * ``/torchrod/contact_<k>/wrench`` (``geometry_msgs/msg/WrenchStamped``), k = 0 .. H-1 for the H contact
      slots, in order of location from the base: the force (f_x, f_y, 0) [N] in the rod's body frame at the
      contact (``header.frame_id`` ``torchrod_body``), torque zero; NaN when the slot holds no contact;
    * ``/torchrod/contact_<k>/arc_length`` (``std_msgs/msg/Float64``): the contact's location s [m] from the base
      (as reported: ``s_model + location_bias``), NaN when the slot is empty.

    A time stamp is ``t`` in nanoseconds, which the format must hold: 0 <= t < 2^32 s in a ROS 1 bag, 0 <= t < 2^31 s
    in a ROS 2 bag (seconds are a 32-bit integer in their headers). An answer whose ``t`` lies outside (``t`` in
    milliseconds since the epoch, 1.7e12) is not written, and ``torchrod stream`` answers that reading with an
    error line saying so; the bag stays readable. A storage that refuses a write (a full disk) is one error.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from ..errors import MissingFileError, OptionsError, ReadingError
from .formats import CURVATURE_ARRAY, bag_formats
from .reading import Reading, to_reading
from .values import quote

__all__ = ["ESTIMATE_TOPIC", "MESSAGE_TYPE", "BagSource", "BagWriter", "require_rosbags", "write_readings"]

MESSAGE_TYPE = CURVATURE_ARRAY
"""The message type of a topic of curvature readings (:data:`torchrod.io.formats.CURVATURE_ARRAY`), the one
:func:`write_readings` writes; a bag topic of any message type of :func:`torchrod.io.formats.bag_formats` is read."""

ESTIMATE_TOPIC = "/torchrod/estimate"
"""The topic of the JSON answers; the contact slots' topics are ``/torchrod/contact_<k>/...``."""


def require_rosbags() -> None:
    """``ValueError`` with the install command when ``rosbags`` is missing."""
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise ReadingError(
            "ROS bags need the rosbags package: pip install 'torchrod[ros]' (or pip install rosbags)"
        ) from None


def _typestore(ros1: bool) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


class BagSource:
    """The readings of ``topic`` in the bag at ``path``, in the bag's time order (module docstring).

    Raises ``ValueError`` (at construction) for a path that is not a bag, a missing topic (the message lists the
    bag's topics) or a topic of another message type."""

    never_waits = True
    """A bag is read from disk: a stream reads it on its own thread (:func:`torchrod.io.stream.stream`)."""

    def __init__(self, path: str | os.PathLike, topic: str, num_gratings: int) -> None:
        require_rosbags()
        from rosbags.highlevel import AnyReader

        self.path, self.topic, self.G = Path(path), topic, num_gratings
        if not self.path.exists():
            raise MissingFileError(f"{self.path}: no such bag")
        try:
            self._reader = AnyReader([self.path], default_typestore=_typestore(self.path.suffix == ".bag"))
            self._reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises its own classes for every kind of bad bag
            raise ReadingError(
                f"{self.path}: not a readable ROS bag ({type(exc).__name__}: {quote(str(exc))})"
            ) from None
        self._connections = [c for c in self._reader.connections if c.topic == topic]
        if not self._connections:
            topics = sorted({c.topic for c in self._reader.connections})
            self._reader.close()
            raise ReadingError(f"{self.path}: no topic {topic!r}; the bag has {quote(topics)}")
        kinds = {c.msgtype for c in self._connections}
        known = bag_formats()
        if len(kinds) != 1 or not kinds <= set(known):
            self._reader.close()
            raise ReadingError(f"{self.path}: topic {topic!r} holds {sorted(kinds)}, not {' or '.join(known)}")
        (kind,) = kinds
        self._message = known[kind].message

    def __iter__(self) -> Iterator[Reading]:
        index = 0
        try:
            messages = self._reader.messages(connections=self._connections)
            while True:
                try:
                    connection, stamp, raw = next(messages)
                except StopIteration:
                    return
                except Exception as exc:  # noqa: BLE001 - rosbags raises its own classes for every kind of damage
                    raise ReadingError(
                        f"{self.path}: the bag is damaged: {self.topic} cannot be read past its message {index} "
                        f"({type(exc).__name__}: {quote(str(exc))}); the messages before it were read"
                    ) from None
                yield self._reading(index, connection, stamp, raw)
                index += 1
        finally:
            self._reader.close()

    def _reading(self, index: int, connection: Any, stamp: int, raw: Any) -> Reading:
        t = stamp * 1e-9
        where = f"message {index} of {self.topic}"
        assert self._message is not None  # (a bag type's entry has its reader)
        try:
            message: Any = self._reader.deserialize(raw, connection.msgtype)  # typed as object by rosbags
            obj = self._message(message, self.G, where)
        except ReadingError as exc:
            return Reading(index, t=t, error=str(exc))
        except Exception as exc:  # noqa: BLE001 - one bad message is one error answer
            return Reading(index, t=t, error=f"{where}: cannot be decoded ({type(exc).__name__})")
        reading = to_reading({"id": index, "t": t, **obj}, self.G)
        if reading.error is not None:
            return Reading(index, t=t, error=f"{where}: {reading.error}")
        return reading


def curvature_array(message: Any, num_gratings: int, where: str) -> dict[str, Any]:
    """The reading object of a ``std_msgs/msg/Float64MultiArray`` message (:data:`MESSAGE_TYPE`; module docstring):
    ``{"curvature": rows}``; :class:`~torchrod.errors.ReadingError` naming the message (``where``) for another
    length or a half-missing grating, another exception for data that are not numbers."""
    data = [float(x) for x in message.data]
    G = num_gratings
    if len(data) != 2 * G:
        raise ReadingError(
            f"{where} holds {len(data)} values; the rod has {G} gratings: give 2G = {2 * G} "
            "(ux, uy per grating, NaN for a missing one)"
        )
    rows: list[Any] = []
    for k in range(G):
        a, b = data[2 * k], data[2 * k + 1]
        if math.isnan(a) != math.isnan(b):
            raise ReadingError(f"{where}: grating {k} has one NaN value: a missing grating is NaN in both")
        rows.append(None if math.isnan(a) else [a, b])
    return {"curvature": rows}


class BagWriter:
    """Estimates into a new bag (module docstring); a context manager. ``slots``: H, the contact slots written per
    reading (the estimator's ``max_forces``, or ``num_forces``).

    A time stamp the format cannot hold (:meth:`stamp`) is a :class:`~torchrod.errors.ReadingError` for that answer
    alone, raised before anything of it is written, so the topics stay aligned and the bag readable. A write the
    storage refuses (a full disk) is an ``OSError`` naming the bag and the cause; the writer then takes no more
    answers (:attr:`failed`), and closing it keeps what the storage still holds."""

    def __init__(self, path: str | os.PathLike, slots: int) -> None:
        require_rosbags()
        self.path, self.slots = Path(path), slots
        if self.path.exists():
            raise OptionsError(f"{self.path} exists already: a bag is never overwritten; give a new path")
        self.ros1 = self.path.suffix == ".bag"
        self.store = _typestore(self.ros1)
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self._writer: Any = Writer1(self.path)  # either bag version's writer
        else:
            from rosbags.rosbag2 import Writer as Writer2

            self._writer = Writer2(self.path, version=9)
        self._count = 0
        self.failed: str | None = None  # why a write failed; no more answers are taken then

    def __enter__(self) -> BagWriter:
        self._writer.open()
        add, types = self._writer.add_connection, self.store.types
        self._estimate = add(ESTIMATE_TOPIC, types["std_msgs/msg/String"].__msgtype__, typestore=self.store)
        self._wrench, self._arc = [], []
        for k in range(self.slots):
            self._wrench.append(
                add(f"/torchrod/contact_{k}/wrench", "geometry_msgs/msg/WrenchStamped", typestore=self.store)
            )
            self._arc.append(add(f"/torchrod/contact_{k}/arc_length", "std_msgs/msg/Float64", typestore=self.store))
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Finish the bag (ROS 1: its index; ROS 2: the commit and ``metadata.yaml``). A storage that refuses (a
        full disk shows up here too) is an ``OSError`` unless a write already failed and said so; either way the
        storage's files are let go."""
        try:
            self._writer.close()
        except Exception as error:  # noqa: BLE001 - the storage's own classes (sqlite3, OSError, rosbags)
            self._release()
            if self.failed is None:
                raise self._storage_error(error) from None

    def _release(self) -> None:
        """Let go of a failed storage's open files (ROS 1: the bag file; ROS 2: the database, rolled back), so that
        nothing stays open on a full disk."""
        writer = self._writer
        try:
            if self.ros1 and getattr(writer, "bio", None) is not None:
                writer.bio.close()
            elif not self.ros1 and getattr(writer, "storage", None) is not None:
                writer.storage.abort()
        except Exception:  # noqa: BLE001, S110 - best effort: the failure itself is reported by the caller
            pass

    def _storage_error(self, exc: BaseException) -> OSError:
        self.failed = f"{type(exc).__name__}: {quote(str(exc))}"
        return OSError(f"--output-bag {self.path}: the bag cannot be written ({self.failed})")

    @property
    def limit(self) -> int:
        """The end of the time stamps [s] the format holds: ROS 1 stores seconds as an unsigned 32-bit integer,
        ROS 2 messages (``builtin_interfaces/Time``) as a signed one; both start at 0."""
        return 2**32 if self.ros1 else 2**31

    def stamp(self, t: float | None) -> int:
        """The bag time stamp [ns] of an answer at ``t`` [s]; None: the answer's index in microseconds, so that
        the order is kept. :class:`~torchrod.errors.ReadingError` for a ``t`` the format cannot hold (0 <= t <
        :attr:`limit`), saying what it may be instead (milliseconds or nanoseconds since the epoch)."""
        if t is None:
            return self._count * 1000
        stamp = round(t * 1e9) if math.isfinite(t) else -1
        if 0 <= stamp < self.limit * 10**9:
            return stamp
        kind = "ROS 1" if self.ros1 else "ROS 2"
        hint = ""
        for unit, factor in (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9)):
            if math.isfinite(t) and 1.0 <= t * factor < self.limit:
                hint = f"; if t is in {unit}, give it in seconds: {t * factor:.9g}"
                break
        raise ReadingError(
            f"t = {t:g} s cannot be a time stamp of a {kind} bag, which holds 0 <= t < {self.limit} s: this answer "
            f"is left out of --output-bag {self.path.name}{hint}"
        )

    def _serialized(self, message: Any, kind: str) -> bytes:
        return self.store.serialize_ros1(message, kind) if self.ros1 else self.store.serialize_cdr(message, kind)

    def write(self, record: Mapping[str, Any], t: float | None) -> None:
        """One answer (an estimate's record or an error record, as written to the JSON lines) at time ``t`` [s]
        (None: the answer's index in microseconds, so that the order is kept). Every message of the answer is made
        before the first is written, so an answer is written whole or not at all (class docstring: errors)."""
        if self.failed is not None:
            raise OSError(f"--output-bag {self.path}: the bag cannot be written ({self.failed})")
        types = self.store.types
        stamp = self.stamp(t)
        self._count += 1
        sec, nsec = divmod(stamp, 10**9)
        try:
            text = json.dumps(record, allow_nan=False)
        except (ValueError, TypeError, OverflowError, RecursionError):
            text = json.dumps({"id": None, "error": "the answer cannot be written as JSON"})
        out = [(self._estimate, self._serialized(types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))]
        forces = record.get("forces") or []
        header_type = types["std_msgs/msg/Header"]
        time_type = types["builtin_interfaces/msg/Time"]
        vector, wrench = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Wrench"]
        for k in range(self.slots):
            nan = math.nan
            force = forces[k] if k < len(forces) else None
            fx, fy, s = (force["fx"], force["fy"], force["s"]) if force else (nan, nan, nan)
            header = (
                header_type(seq=self._count, stamp=time_type(sec=sec, nanosec=nsec), frame_id="torchrod_body")
                if self.ros1
                else header_type(stamp=time_type(sec=sec, nanosec=nsec), frame_id="torchrod_body")
            )
            message = types["geometry_msgs/msg/WrenchStamped"](
                header=header,
                wrench=wrench(force=vector(x=fx, y=fy, z=0.0), torque=vector(x=0.0, y=0.0, z=0.0)),
            )
            out.append((self._wrench[k], self._serialized(message, "geometry_msgs/msg/WrenchStamped")))
            out.append((self._arc[k], self._serialized(types["std_msgs/msg/Float64"](data=s), "std_msgs/msg/Float64")))
        try:
            for connection, raw in out:
                self._writer.write(connection, stamp, raw)
        except Exception as exc:  # noqa: BLE001 - the storage's own classes (sqlite3, OSError, rosbags)
            raise self._storage_error(exc) from None


def write_readings(path: str | os.PathLike, topic: str, readings: list[tuple[float, list[Any]]]) -> None:
    """A bag of readings (module docstring): ``(t [s], curvature)`` pairs, the curvature G ``[ux, uy]`` pairs or
    None per grating. For tests and for making example bags; a ROS 1 bag when ``path`` ends in ``.bag``."""
    require_rosbags()
    import numpy as np

    path = Path(path)
    ros1 = path.suffix == ".bag"
    store = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1
    else:
        from rosbags.rosbag2 import Writer as Writer2
    writer: Any = Writer1(path) if ros1 else Writer2(path, version=9)
    array, layout = store.types[MESSAGE_TYPE], store.types["std_msgs/msg/MultiArrayLayout"]
    with writer:
        connection = writer.add_connection(topic, MESSAGE_TYPE, typestore=store)
        for t, curvature in readings:
            data = np.array([x for pair in curvature for x in (pair if pair is not None else (math.nan, math.nan))])
            message = array(layout=layout(dim=[], data_offset=0), data=data.astype(np.float64))
            raw = store.serialize_ros1(message, MESSAGE_TYPE) if ros1 else store.serialize_cdr(message, MESSAGE_TYPE)
            writer.write(connection, round(t * 1e9), raw)
