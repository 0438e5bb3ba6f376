"""PTP (ISO 15740) with the Canon EOS extension: an I/O-free codec, USB and PTP/IP transports, and a `Camera` on top."""
