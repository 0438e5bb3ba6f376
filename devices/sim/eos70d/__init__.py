"""A simulated Canon EOS 70D: a PTP responder reached through a pure-Python pyusb backend or PTP/IP on 127.0.0.1."""
