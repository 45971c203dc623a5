"""``gyrocal replay``: recorded traffic is just another transport (gpsfake for IMUs).

- source.py: a recording (python-can log, serial capture, or any log a reader takes) as a stream of
  unit messages and sample blocks, in recorded order;
- unit.py: the unit as far as the recording allows: it answers HELLO_REQUEST and COEFF_READ, and
  acks a COEFF_WRITE as *recorded* (the push is written to the replay's output, nothing is sent),
  then compensates its recorded output with the pushed set as a unit would;
- link.py: the replay Link (link kind ``replay``) feeding the daemon's ring and inbox;
- run.py: the daemon's own Engine on a simulated clock (the recording's unit time), full speed;
- pty_player.py: ``--pty``, the recording played into a pty in real time for a live daemon.
"""
