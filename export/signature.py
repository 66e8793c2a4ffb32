"""An Ed25519 signature over an export's traceability chain (``chain.dsse.json`` beside ``chain.json``).

The signature is a DSSE envelope (https://github.com/secure-systems-lab/dsse), the form in-toto tools
read: the payload is ``chain.json``'s bytes (an in-toto Statement), the signature is over DSSE's
pre-authentication encoding of the payload type and the payload, and the key's id is the SHA-256 of its
raw 32-byte public key. Keys are PEM files, as ``openssl genpkey -algorithm ed25519`` writes them (the
private key, PKCS#8 without a passphrase) and ``openssl pkey -pubout`` (the public key).

A consistent rewrite of every manifest (chain.json, the envelope's payload) keeps the chain intact but not
the signature: only the private key makes a signature that the public key accepts. Key files are
untrusted input like any other: a file that is not such a key is a :class:`SignatureError` in one line.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from embedrl.common import atomic_write, read_json
from embedrl.export.chain import MANIFEST
from embedrl.export.errors import ExportError

ENVELOPE = "chain.dsse.json"
PAYLOAD_TYPE = "application/vnd.in-toto+json"
MAX_KEY_BYTES = 64 * 2**10


class SignatureError(ExportError):
    """A key file that is not an Ed25519 key of the kind asked for."""


@dataclass(frozen=True)
class Signature:
    """What can be said of an export's signature. Trust comes only from the public key the user names
    (``--key``): without it nothing is verified, and nothing read from the envelope (its key id included) is
    shown as if it were."""

    state: str
    """``valid`` (checked against the user's key), ``invalid``, ``unsigned`` or ``unchecked`` (an envelope,
    no key to check it with): the last two are warnings, neither a pass nor a failure."""
    detail: str

    @property
    def passed(self) -> bool:
        """Whether nothing failed (an unchecked or missing signature did not fail: it was not checked)."""
        return self.state != "invalid"

    @property
    def verified(self) -> bool:
        """Whether the signature was checked against the user's key and holds: the only PASS."""
        return self.state == "valid"

    def to_json(self) -> dict[str, Any]:
        return {"state": self.state, "passed": self.passed, "verified": self.verified, "detail": self.detail}


def pae(payload_type: str, payload: bytes) -> bytes:
    """DSSE's pre-authentication encoding: what is signed, so the type cannot be swapped for another."""
    kind = payload_type.encode()
    return b"DSSEv1 %d %s %d %s" % (len(kind), kind, len(payload), payload)


def load_private_key(key_file: Path) -> Any:
    """The Ed25519 private key in ``key_file``: SignatureError (one line) for anything else."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import load_pem_private_key

    try:
        key = load_pem_private_key(_key_bytes(key_file), password=None)
    except (ValueError, TypeError) as exc:
        raise SignatureError(
            f"--sign {key_file}: not a PEM private key without a passphrase ({exc})"
        ) from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SignatureError(
            f"--sign {key_file}: a {type(key).__name__.removeprefix('_')}, not an Ed25519 key"
        )
    return key


def sign(export_dir: Path, key: Any) -> str:
    """Sign the export's chain.json with ``key`` (from :func:`load_private_key`); the key's id."""
    payload = (export_dir / MANIFEST).read_bytes()
    keyid = key_id(key.public_key())
    signature = base64.b64encode(key.sign(pae(PAYLOAD_TYPE, payload))).decode()
    envelope = {
        "payloadType": PAYLOAD_TYPE,
        "payload": base64.b64encode(payload).decode(),
        "signatures": [{"keyid": keyid, "sig": signature}],
    }
    text = json.dumps(envelope, indent=2) + "\n"
    atomic_write(export_dir / ENVELOPE, lambda tmp: tmp.write_text(text))
    return keyid


def load_public_key(key_file: Path) -> Any:
    """The Ed25519 public key in ``key_file``: SignatureError (one line) for anything else."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
    from cryptography.hazmat.primitives.serialization import load_pem_public_key

    try:
        key = load_pem_public_key(_key_bytes(key_file))
    except (ValueError, TypeError) as exc:
        raise SignatureError(f"--key {key_file}: not a PEM public key ({exc})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise SignatureError(
            f"--key {key_file}: a {type(key).__name__.removeprefix('_')}, not an Ed25519 key"
        )
    return key


def key_id(public_key: Any) -> str:
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    return hashlib.sha256(public_key.public_bytes(Encoding.Raw, PublicFormat.Raw)).hexdigest()


def check(export_dir: Path, public_key: Any | None) -> Signature:
    """The state of the export's signature: checked against ``public_key`` if given (a key given and no
    signature is invalid: a signature was expected); never raises for a damaged envelope."""
    envelope_file = export_dir / ENVELOPE
    if not envelope_file.exists():
        if public_key is not None:
            return Signature("invalid", f"unsigned (no {ENVELOPE}), but a key was given to check it")
        return Signature("unsigned", f"not signed (no {ENVELOPE}): nothing vouches for who made this export")
    try:
        payload, keyid, sig = _read_envelope(envelope_file)
    except (ValueError, TypeError, KeyError, OSError, binascii.Error) as exc:
        return Signature("invalid", f"{ENVELOPE} is not a signature envelope ({exc})")
    try:
        manifest = (export_dir / MANIFEST).read_bytes()
    except OSError as exc:
        return Signature("invalid", f"{MANIFEST} cannot be read ({exc.strerror})")
    if payload != manifest:
        return Signature("invalid", f"{MANIFEST} changed since it was signed (sign the export again)")
    if public_key is None:  # the envelope's key id is the envelope's claim: not shown as a fact
        return Signature(
            "unchecked",
            "signature not checked: no trusted key given (--key PUB.pem, the signer's public key)",
        )
    if keyid != key_id(public_key):
        return Signature(
            "invalid", f"signed by key {keyid[:16]}..., not by the key given ({key_id(public_key)[:16]}...)"
        )
    from cryptography.exceptions import InvalidSignature

    try:
        public_key.verify(sig, pae(PAYLOAD_TYPE, payload))
    except InvalidSignature:
        return Signature("invalid", f"the signature does not match {MANIFEST}: rewritten since it was signed")
    return Signature("valid", f"signed by key {keyid[:16]}... and valid")


def _read_envelope(path: Path) -> tuple[bytes, str, bytes]:
    data = read_json(path)
    if data["payloadType"] != PAYLOAD_TYPE:
        raise ValueError(f"payloadType {data['payloadType']!r}, expected {PAYLOAD_TYPE}")
    signatures = data["signatures"]
    if not isinstance(signatures, list) or len(signatures) != 1:
        raise ValueError("not exactly one signature")
    keyid = signatures[0]["keyid"]
    if not isinstance(keyid, str):
        raise ValueError(f"keyid {keyid!r} is not a text")
    payload = base64.b64decode(data["payload"], validate=True)
    return payload, keyid, base64.b64decode(signatures[0]["sig"], validate=True)


def _key_bytes(path: Path) -> bytes:
    """A key file's bytes, read only if it is a regular file of at most MAX_KEY_BYTES (SignatureError)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise SignatureError(f"{path}: cannot read the key ({exc.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # before fdopen, which refuses a folder with another error
        os.close(fd)
        raise SignatureError(f"{path}: not a key file (not a regular file)")
    with os.fdopen(fd, "rb") as f:
        data = f.read(MAX_KEY_BYTES + 1)
    if len(data) > MAX_KEY_BYTES:
        raise SignatureError(f"{path}: more than {MAX_KEY_BYTES:,} bytes, not a key file")
    return data
