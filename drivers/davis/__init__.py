"""The DAVIS240/DAVIS346 USB driver: models, register protocol, word decoder/encoder, transport, device."""
