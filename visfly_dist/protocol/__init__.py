"""The wire shared by scene workers and the aggregator: messages, msgpack codec, keys, sessions."""

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import PROTOCOL_VERSION, decode, encode, error_message
from visfly_dist.protocol.messages import (
    Health,
    LoadScene,
    SampleSpawn,
    ScenePoses,
    StepRequest,
    UnloadScene,
    parse_request,
    split_step_result,
    step_message,
)

__all__ = [
    "CameraSpec", "PROTOCOL_VERSION", "decode", "encode", "error_message", "Health", "LoadScene",
    "SampleSpawn", "ScenePoses", "StepRequest", "UnloadScene", "parse_request", "split_step_result", "step_message",
]
