"""The CAN wire's description, shared by the host drivers and the simulated box.

* :mod:`drivers.protocol.frames` — classical CAN frame bit lengths (worst-case and exact
  bit stuffing), for the bus-load budget and the simulated wire;
* :mod:`drivers.protocol.batch` — a batch of frames as one NumPy record array (the
  ``hrm_ipc`` datagram's record), with views of the TPDO and RPDO fields;
* :mod:`drivers.protocol.cia301` — the CANopen communication profile: COB-IDs, NMT,
  heartbeat, SYNC, EMCY, SDO frames and abort codes, PDO mapping entries;
* :mod:`drivers.protocol.cia402` — the drive profile: objects, controlword commands,
  statusword, the state machine as one transition table, our PDO payloads.

Pure definitions and frame builders/parsers: nothing here touches a bus.
"""
