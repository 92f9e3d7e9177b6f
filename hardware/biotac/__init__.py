"""BioTac over SPI: protocol and the `SpiTransport` seam (`protocol`), the reader that identifies and
samples the sensors (`client`), Cheetah transport (`transport`), SPI-over-TCP bridge (`bridge`) and
simulated sensors on a bus (`sim`)."""
