"""What our output channels hold: the records we write (`records`), the message definitions
they follow (`schema_files`, over `schemas/`), and reading an annotated log back (`reader`)."""
