"""The moulder: several heads (each one :class:`~controller.service.service.Service`), one feed."""
