"""Hardware in the loop: DWM1001 codecs (TIERS autocalibration firmware, PANS shell and TLV),
a pyserial transport, drivers, a byte-exact emulator, session recording/replay, and the
backend that runs the environment on real (or emulated) anchors."""
