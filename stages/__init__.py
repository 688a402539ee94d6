"""One module per pipeline stage: each reads artifacts, calls the library, writes artifacts."""
