"""Figures of merit for designing lighting patterns (docs/designer.md): measurement noise and multiplexing gain."""
