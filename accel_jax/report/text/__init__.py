"""What the `accel-jax` commands print, one module per command: pure functions from results
to lines of text (and to the records of the JSON documents the CLI writes). No click, no
figures, no file writing, no change of JAX's settings: the CLI parses, calls the library,
prints these lines and writes the files.

- `help`: every command's description and every option's help, as `--help` prints them;
- `info`: the closed-form characteristics of the reference devices;
- `tolerance`: an implausible option's message, the limits table, its legend and the
  passport check, and the JSON payload;
- `identify`: several records of one device (small steps and stop-level records);
- `diagnose`: the notes on options that did not apply to the records given;
- `noise`: the IEEE terms and the effects of a static record, and its exports.
"""
