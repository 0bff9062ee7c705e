"""What a person reads: the report (Markdown and HTML, its tables and figures), the rerun recording,
batch summaries and exports to motion-capture formats."""
