"""Scripts behind ``narf bench``: each writes JSON, Markdown and PNG results and returns a dict."""
