"""mrcert: certify and stress-test visual perception models against camera motion."""

__version__ = "0.1.0"
