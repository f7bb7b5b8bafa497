# Sourced by the interop scripts that drive `axiscomp console` in tmux: the session `console`
# on the server "${tmx[@]}" names; the sourcing script defines fail MESSAGE.
# screen: the pane's text. expect SECONDS TEXT...: wait until the screen shows every TEXT.
# keys KEY...: tmux send-keys, then a moment for the console to draw.
screen() { "${tmx[@]}" capture-pane -p -t console; }
expect() {
  local secs=$1; shift
  local end=$((SECONDS + secs)) text missing
  while :; do
    text=$(screen)
    missing=""
    for want in "$@"; do
      grep -qF -- "$want" <<<"$text" || { missing=$want; break; }
    done
    [ -z "$missing" ] && return 0
    [ "$SECONDS" -ge "$end" ] && fail "within ${secs} s the screen did not show \"$missing\""
    sleep 0.3
  done
}
keys() { "${tmx[@]}" send-keys -t console "$@"; sleep 0.2; }
