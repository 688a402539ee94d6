"""The synthetic world `dali synth` scans: the car pool (`cars`), the scene layout (`scene`) and
the scanning (`scan`). Everything random comes from the generator it is given, so a frame is
the same whatever the number of frames, their order or the worker count."""
