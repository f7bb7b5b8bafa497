//! CANopen master for the follower drive (DESIGN §6): NMT, heartbeat consumer, SDO client,
//! PDO mapping, SYNC, EMCY and the CiA 402 drive state machine.
