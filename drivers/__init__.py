"""Event-camera sources for edi-live: the live DAVIS driver over pyusb, its emulator, and AEDAT4 replay.

Drivers know nothing of EDI, the ring buffer or ZeroMQ; they yield `edi_live.datatypes.Packet`s.
Submodules are imported lazily, so `import drivers` does not load pyusb.
"""
