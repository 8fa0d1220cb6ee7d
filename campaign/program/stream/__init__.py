"""A tracker's log matched back to a program's stops (`campaign import --stream`): read in blocks
(logread), still windows (windows), aligned to the stops (align), stored as a campaign (importer)."""

from campaign.program.stream.importer import StreamResult, import_stream  # noqa: F401
