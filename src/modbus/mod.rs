//! Modbus TCP: the client link (timeouts, reconnect), server scaffolding, register codecs.
