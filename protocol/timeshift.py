"""Moving a message in time: every timestamp field (``TimeNs``, marked EPOCH_TIME in protocol.messages)
shifted by one offset, durations left alone. A replay shifted to the present keeps every relation
between timestamps (capture before publish, IMU grid, latency) exactly as recorded."""
from __future__ import annotations

import typing

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from protocol.messages import EPOCH_TIME, Message

M = typing.TypeVar("M", bound=Message)


def _marked(annotation) -> bool:
    """True if EPOCH_TIME appears in the annotation (also inside Optional[...] and the like)."""
    if typing.get_origin(annotation) is typing.Annotated:
        if any(m is EPOCH_TIME for m in annotation.__metadata__):
            return True
    return any(_marked(a) for a in typing.get_args(annotation))


def _is_timestamp(info: FieldInfo) -> bool:
    return any(m is EPOCH_TIME for m in info.metadata) or _marked(info.annotation)


def _shifted(value, offset_ns: int):
    if isinstance(value, BaseModel):
        return shift_times(value, offset_ns)
    if isinstance(value, list):
        return [_shifted(v, offset_ns) for v in value]
    return value


def shift_times(msg: M, offset_ns: int) -> M:
    """A copy of ``msg`` (any protocol model, nested models included) with every timestamp moved by
    ``offset_ns``. Raises ValueError if a timestamp would fall before the epoch."""
    update = {}
    for name, info in type(msg).model_fields.items():
        value = getattr(msg, name)
        if value is None:
            continue
        if _is_timestamp(info):
            moved = int(value) + int(offset_ns)
            if moved < 0:
                raise ValueError(f"{type(msg).__name__}.{name}: {value} shifted by {offset_ns} ns is before the epoch")
            update[name] = moved
        else:
            moved = _shifted(value, offset_ns)
            if moved is not value:
                update[name] = moved
    # model_copy skips validation: the shifted values keep every constraint but ge=0, checked above.
    return msg.model_copy(update=update) if update else msg
