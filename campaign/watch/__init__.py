"""`campaign watch`: the live page of a run (server, API, bundled assets); docs/watch.md."""
