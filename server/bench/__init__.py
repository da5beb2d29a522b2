"""Benchmarks of the browser server: `kinetix bench server` (server), `python -m server.bench.agent`,
`python -m server.bench.recording`."""
