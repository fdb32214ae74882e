"""zagv wire protocol: message Structs, key expressions and the codec shared by every service."""

from proto import messages as _messages
from proto.codec import ProtoDecodeError, array, decode, decode_as, encode, to_json
from proto.keys import DEFAULT_ROBOT_ID, Keys
from proto.messages import *  # noqa: F403

__all__ = [
    "DEFAULT_ROBOT_ID",
    "Keys",
    "ProtoDecodeError",
    "array",
    "decode",
    "decode_as",
    "encode",
    "to_json",
    *[n for n, v in vars(_messages).items() if isinstance(v, type) and issubclass(v, _messages.Message)],
]
