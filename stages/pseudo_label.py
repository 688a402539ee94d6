"""Stage: pseudo_label (library call + artifact I/O). Filled in by its issue."""
