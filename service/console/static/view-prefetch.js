// A classic script, run as soon as the head is read: the 3D view's mesh document is fetched,
// and the WebGL context made, while three.js loads (view.js takes both; the context is made
// when the main thread is next idle, so that the page is not held up).
window.pwmFirstMesh = fetch(`/console/api/versions/${encodeURIComponent(new URLSearchParams(location.search).get("v") || "latest")}/mesh`);
window.pwmCanvas = document.createElement("canvas");
window.pwmContext = new Promise((resolve) => setTimeout(() => resolve(
  window.pwmCanvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true })), 0));
