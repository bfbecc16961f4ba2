// MathJax 3's configuration, read when assets/mathjax/tex-chtml.js loads right after this file (both
// from mkdocs.yml's extra_javascript; docs/hooks.py puts MathJax in the site). Only math markup is
// typeset: pymdownx.arithmatex's spans on the markdown pages (it writes \( \) and \[ \]), and the
// rendered markdown cells of the notebook pages (whose source writes $ $ and $$ $$); code, its
// outputs and the rest of the page are left as they are, dollar signs included.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
  },
  startup: {
    elements: [".arithmatex", ".jp-RenderedMarkdown"],
  },
};
