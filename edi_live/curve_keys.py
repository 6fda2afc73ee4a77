"""ZeroMQ CURVE certificate files: the keys in the ZPL text that `zmq.auth.create_certificates` writes
(`public-key = "..."`, `secret-key = "..."`, Z85), for the publisher's --curve-secret-key and the subscribers'
--curve-server-key (generating them needs zmq: edi_live.publisher.generate_curve_keys). Read through
config_file.read_limited, so that a key given as a pipe (bash's <(...)) is read and a FIFO that nothing writes to
ends in an error instead of blocking open() for ever, as zmq.auth's reader did."""

from __future__ import annotations

import os
from pathlib import Path

from edi_live.config_file import read_limited
from edi_live.errors import PublishError

MAX_KEY_FILE_BYTES = 64 << 10  # a certificate is ~300 bytes
_Z85 = frozenset(b"0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#")


def check_z85(key: bytes, what: str) -> bytes:
    """The key if it is 40 Z85 characters (32 bytes), else ValueError: libzmq says only 'Invalid argument'."""
    if len(key) != 40 or not _Z85.issuperset(key):
        raise ValueError(f"{what} is not a 40-character Z85 key (got {len(key)} characters)")
    return key


def load_certificate(path: str | os.PathLike) -> tuple[bytes, bytes | None]:
    """(public key, secret key or None for a public certificate), both Z85. OSError if the file cannot be read;
    ValueError if it is too large or holds no public key."""
    keys: dict[bytes, bytes] = {}
    for line in read_limited(path, MAX_KEY_FILE_BYTES).splitlines():
        name, sep, value = line.strip().partition(b"=")
        name = name.strip()
        if sep and name in (b"public-key", b"secret-key") and name not in keys:
            keys[name] = value.strip(b" \t'\"")
    if not keys.get(b"public-key"):
        raise ValueError("no public-key line: not a ZeroMQ certificate file")
    secret = keys.get(b"secret-key") or None
    return check_z85(keys[b"public-key"], "its public-key"), secret and check_z85(secret, "its secret-key")


def load_secret_key(path: str | os.PathLike) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys from a ZeroMQ certificate file; PublishError if unusable."""
    path = Path(path)
    try:
        public, secret = load_certificate(path)
    except Exception as exc:  # OSError for a missing file, ValueError for a malformed one
        why = getattr(exc, "strerror", None) or exc
        raise PublishError(f"cannot read CURVE secret key {path}: {why}; generate one with "
                           "`python -m edi_live.publisher --gen-curve-keys DIR`") from exc
    if not secret:
        raise PublishError(f"CURVE key file {path} holds no secret key (pass the *.key_secret file, "
                           "not the public *.key)")
    return public, secret
