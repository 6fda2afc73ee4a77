"""Preloaded only by the decoding children's forkserver (see `drivers.decoding_child._context`).

multiprocessing's forkserver can run code only by importing the modules named in its preload list, so importing
this module is the call site of `warm_decoder_or_warn()` in the server: every child forked from it then starts
with the AEDAT4 reader's kernels loaded. A failure is logged as a warning (the server's stderr is the node's) and
only costs each child ~0.4 s before its first packet. Nothing else imports this module.
"""

from __future__ import annotations

from drivers.decoding_child import warm_decoder_or_warn

warm_decoder_or_warn()
