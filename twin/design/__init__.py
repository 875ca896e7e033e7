"""Figures of merit for designing lighting patterns (issue #17): measurement noise and multiplexing gain."""
