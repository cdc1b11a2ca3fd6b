"""A digest of the messages a log holds, in the order they were written.

:class:`MessageDigest` counts messages and hashes each one's topic, log time and payload bytes
(SHA-256). A :class:`~rollingstar.logs.writer.LogWriter` made with ``digest=True`` keeps one over
everything it writes; the same digest over a log read back in write order
(:meth:`~rollingstar.logs.reader.LogReader.written_messages`) tells whether its first messages are
exactly those (``rollingstar run --resume`` checks a partial output this way).
"""
from __future__ import annotations

import hashlib
import struct


class MessageDigest:
    """Count and SHA-256 of messages added in order."""

    def __init__(self) -> None:
        self.count = 0
        self._sha = hashlib.sha256()

    def add(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """One message: its topic, log time and payload, each length-delimited."""
        name = topic.encode()
        self._sha.update(struct.pack("<QQ", len(name), int(log_time_ns)) + name)
        self._sha.update(struct.pack("<Q", len(data)))
        self._sha.update(data)
        self.count += 1

    def hexdigest(self) -> str:
        return self._sha.hexdigest()
