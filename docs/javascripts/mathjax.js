// MathJax settings for pymdownx.arithmatex (generic mode): typeset only the spans and
// blocks it marks with class "arithmatex", which hold \( ... \) and \[ ... \].
window.MathJax = {
  tex: { inlineMath: [["\\(", "\\)"]], displayMath: [["\\[", "\\]"]], processEscapes: true, processEnvironments: true },
  options: { ignoreHtmlClass: ".*|", processHtmlClass: "arithmatex" }
};
