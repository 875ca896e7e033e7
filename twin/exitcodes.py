"""The exit codes of every `hemicube` command, one table (README, "Exit codes"; `hemicube --help` prints it)."""
from __future__ import annotations

EXIT_OK, EXIT_MISSED, EXIT_USAGE, EXIT_IO = 0, 1, 2, 3
EXIT_CODES = {EXIT_OK: "done; for validate, compare and calibrate --validate: every check and goal met",
              EXIT_MISSED: "the run finished and a goal or threshold was missed (its report says which)",
              EXIT_USAGE: "bad usage or input: an option, a path, a file's content, a device this machine lacks",
              EXIT_IO: "the system refused a read or a write (read-only place, full disk, permissions), or a "
                       "file written fails its checksum"}
