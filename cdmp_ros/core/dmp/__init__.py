"""DMPs and CDMPs (paper 000): basis, tanh transform, batch integration, the streaming stepper
and PI2."""
