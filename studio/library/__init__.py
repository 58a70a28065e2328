"""The serve library a robot controller reads, serve selection and match statistics."""
