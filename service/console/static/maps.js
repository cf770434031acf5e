// What makes a map readable, shared by the site, coverage and 3D pages, drawn as SVG (found by
// its data-role, read as text): a colour bar with its quantity and unit, a scale bar in m or km,
// a north arrow at the angle north has in the map, axes with ticks and units, and ticks and
// lengths formatted to the digits their step needs.

const NS = "http://www.w3.org/2000/svg";
let gradients = 0;

// An SVG element with attributes (and text).
export function svg(tag, attributes = {}, text) {
  const node = document.createElementNS(NS, tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  if (text !== undefined) node.textContent = text;
  return node;
}

// The 1, 2 or 5 x 10^n step that cuts span into about `count` parts.
export function niceStep(span, count = 5) {
  if (!(span > 0) || !Number.isFinite(span)) return 1;
  const rough = span / count;
  const power = 10 ** Math.floor(Math.log10(rough));
  const factor = [1, 2, 5, 10].find((f) => f * power >= rough);
  return factor * power;
}

// Tick values at multiples of a nice step within [lo, hi], and that step.
export function ticks(lo, hi, count = 5) {
  const step = niceStep(hi - lo, count);
  const values = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) values.push(v);
  return { values, step };
}

// A tick's text: as many decimals as its step needs, no more (0.0034 with step 0.001 -> "0.003").
export function tickText(value, step) {
  const decimals = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  const text = value.toFixed(Math.min(decimals, 10));
  return /^-0(\.0*)?$/.test(text) ? text.slice(1) : text;
}

// A length in metres as a reader says it: metres below 1 km, km above.
export function lengthText(metres) {
  if (metres >= 1000) return `${tickText(metres / 1000, niceStep(metres / 1000, 1))} km`;
  return `${tickText(metres, niceStep(metres, 1))} m`;
}

// A quantity's label with its unit: "height (m)", or "albedo (no unit)".
export function withUnit(label, unit) {
  return `${label} (${unit || "no unit"})`;
}

// A horizontal colour bar: the colour map's samples (RGB 0-255, low to high) between lo and hi,
// ticked, titled with the quantity and its unit; `note` under it (e.g. "grey: unknown").
export function colourBar({ label, unit, lo, hi, stops, width = 300, note = "" }) {
  const id = `pwm-gradient-${++gradients}`;
  const bar = svg("svg", { width, height: note ? 62 : 48, class: "colour-bar", "data-role": "colour-bar",
    "data-unit": unit || "", "data-min": lo, "data-max": hi });
  const gradient = svg("linearGradient", { id, x1: 0, x2: 1, y1: 0, y2: 0 });
  stops.forEach((rgb, k) => gradient.append(svg("stop", { offset: k / (stops.length - 1),
    "stop-color": `rgb(${rgb.join(",")})` })));
  const defs = svg("defs");
  defs.append(gradient);
  const left = 10, right = width - 10, top = 18, height = 12;
  bar.append(defs, svg("text", { x: left, y: 12, class: "title" }, withUnit(label, unit)),
    svg("rect", { x: left, y: top, width: right - left, height, fill: `url(#${id})`, class: "frame" }));
  if (lo !== null && hi !== null && hi > lo) {
    const { values, step } = ticks(lo, hi, 5);
    for (const v of values) {
      const x = left + ((v - lo) / (hi - lo)) * (right - left);
      bar.append(svg("line", { x1: x, x2: x, y1: top + height, y2: top + height + 4, class: "tick" }),
        svg("text", { x, y: top + height + 15, "text-anchor": "middle" }, tickText(v, step)));
    }
  }
  if (note) bar.append(svg("text", { x: left, y: top + height + 30, class: "note" }, note));
  return bar;
}

// A legend of categories for a map of classes (the hazard map): [label, [r, g, b]] pairs.
export function classBar({ label, classes, width = 300 }) {
  const bar = svg("svg", { width, height: 40, class: "colour-bar", "data-role": "colour-bar", "data-unit": "class" });
  bar.append(svg("text", { x: 10, y: 12, class: "title" }, label));
  let x = 10;
  for (const [name, rgb] of classes) {
    bar.append(svg("rect", { x, y: 20, width: 12, height: 12, fill: `rgb(${rgb.join(",")})`, class: "frame" }),
      svg("text", { x: x + 16, y: 30 }, name));
    x += 22 + 7 * name.length;
  }
  return bar;
}

// A scale bar at (x, y) (its left end; the bar's baseline): the longest nice length within
// `maxPx` pixels at `metresPerPx`, labelled in m or km.
export function scaleBar(x, y, metresPerPx, maxPx = 100) {
  // the largest 1, 2 or 5 x 10^n within maxPx (halving the nice step above it gave 2.5 x 10^n)
  const most = maxPx * metresPerPx;
  const power = 10 ** Math.floor(Math.log10(most));
  const length = [5, 2, 1].map((f) => f * power).find((v) => v <= most * (1 + 1e-9)) ?? power;
  const px = length / metresPerPx;
  const group = svg("g", { class: "scale-bar", "data-role": "scale-bar", "data-metres": length });
  group.append(svg("rect", { x: x - 4, y: y - 18, width: px + 8, height: 24, class: "badge" }),
    svg("rect", { x, y: y - 4, width: px / 2, height: 4, class: "dark" }),
    svg("rect", { x: x + px / 2, y: y - 4, width: px / 2, height: 4, class: "light" }),
    svg("text", { x: x + px / 2, y: y - 7, "text-anchor": "middle" }, lengthText(length)));
  return group;
}

// A north arrow centred at (x, y) pointing along the map direction [dx, dy] (x right, y up,
// as the map's own axes); at a pole (no direction) a mark that says so.
export function northArrow(x, y, direction) {
  const group = svg("g", { class: "north-arrow", "data-role": "north-arrow" });
  group.append(svg("circle", { cx: x, cy: y, r: 19, class: "badge" }));
  if (!direction) {
    group.append(svg("text", { x, y: y + 4, "text-anchor": "middle" }, "pole"));
    group.dataset.angle = "";
    return group;
  }
  // SVG's y runs down: the angle clockwise from up
  const angle = (Math.atan2(direction[0], direction[1]) * 180) / Math.PI;
  group.dataset.angle = angle.toFixed(1);
  const arrow = svg("g", { transform: `rotate(${angle.toFixed(2)} ${x} ${y})` });
  arrow.append(svg("path", { d: `M ${x} ${y - 3} L ${x + 5} ${y + 14} L ${x} ${y + 10} L ${x - 5} ${y + 14} Z`, class: "dark" }),
    svg("text", { x, y: y - 5, "text-anchor": "middle", class: "north" }, "N"));
  group.append(arrow);
  return group;
}

// Ticked axes around the plot box {left, top, width, height} spanning x [x0, x1] and y [y0, y1]
// (y up), titled xLabel and yLabel (with their units).
export function axes(box, { x0, x1, y0, y1, xLabel, yLabel, count = 5 }) {
  const group = svg("g", { class: "axes", "data-role": "axes" });
  group.append(svg("rect", { x: box.left, y: box.top, width: box.width, height: box.height, class: "outline" }));
  const bottom = box.top + box.height;
  const xs = ticks(x0, x1, count);
  for (const v of xs.values) {
    const px = box.left + ((v - x0) / (x1 - x0)) * box.width;
    group.append(svg("line", { x1: px, x2: px, y1: bottom, y2: bottom + 4, class: "tick" }),
      svg("text", { x: px, y: bottom + 15, "text-anchor": "middle" }, tickText(v, xs.step)));
  }
  const ys = ticks(y0, y1, count);
  for (const v of ys.values) {
    const py = bottom - ((v - y0) / (y1 - y0)) * box.height;
    group.append(svg("line", { x1: box.left - 4, x2: box.left, y1: py, y2: py, class: "tick" }),
      svg("text", { x: box.left - 6, y: py + 4, "text-anchor": "end" }, tickText(v, ys.step)));
  }
  group.append(svg("text", { x: box.left + box.width / 2, y: bottom + 30, "text-anchor": "middle", class: "title" }, xLabel));
  const yTitle = svg("text", { x: 0, y: 0, "text-anchor": "middle", class: "title",
    transform: `translate(12 ${box.top + box.height / 2}) rotate(-90)` }, yLabel);
  group.append(yTitle);
  return group;
}
