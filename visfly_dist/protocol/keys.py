"""Key expressions of the wire: the one place that builds them.

Everything of a run lives under ``visfly/<run_id>/`` so two runs on one network never meet.
"""

from __future__ import annotations

import re

from visfly_dist.errors import ConfigError

ROOT = "visfly"
MAX_CHUNK_CHARS = 256
CHUNK_PATTERN = r"[A-Za-z0-9_.\-]"
"""The characters a key chunk may hold (a regex character class)."""
_CHUNK = re.compile(CHUNK_PATTERN + "+")


def check_chunk(value: str, what: str) -> str:
    """Return ``value`` if it is a safe single key-expression chunk, else raise ConfigError.

    The whole string must match (a trailing newline is refused) and hold at most
    :data:`MAX_CHUNK_CHARS` characters.
    """
    if not isinstance(value, str) or len(value) > MAX_CHUNK_CHARS or not _CHUNK.fullmatch(value):
        shown = value if not isinstance(value, str) or len(value) <= 80 else value[:80] + "..."
        raise ConfigError(f"{what}={shown!r} must be a non-empty string of at most {MAX_CHUNK_CHARS} letters, "
                          "digits, '_', '.', '-'")
    return value


def worker_rpc(run_id: str, worker_id: str) -> str:
    """The queryable a worker serves all its requests on."""
    return f"{ROOT}/{check_chunk(run_id, 'run_id')}/worker/{check_chunk(worker_id, 'worker_id')}/rpc"


def worker_alive(run_id: str, worker_id: str) -> str:
    """The liveliness token a worker holds while it is alive and serving."""
    return f"{ROOT}/{check_chunk(run_id, 'run_id')}/alive/worker/{check_chunk(worker_id, 'worker_id')}"


def trainer_alive(run_id: str) -> str:
    """The liveliness token the trainer of a run holds while its env is open (one trainer per run)."""
    return f"{ROOT}/{check_chunk(run_id, 'run_id')}/alive/trainer"


def workers_alive_pattern(run_id: str) -> str:
    """Pattern matching the liveliness tokens of every worker of one run."""
    return f"{ROOT}/{check_chunk(run_id, 'run_id')}/alive/worker/*"


def worker_id_from_alive_key(key: str) -> str:
    """The worker id at the end of a liveliness key."""
    return str(key).rsplit("/", 1)[-1]
