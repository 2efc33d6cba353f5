"""Before the files: what to record (:mod:`.plan`) and recording it through
Micro-Manager."""
