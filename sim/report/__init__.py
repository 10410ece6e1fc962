"""What people read: figures in the paper's layout (``plots``) and the plain-text
summaries shared by the library and the commands (``textfmt``)."""
