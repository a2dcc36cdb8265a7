// PLACEHOLDER: alerting is not built yet. The nav entry and this route stay hidden until the
// API answers /api/v1/alerts (main.js feature-detects it); then this page is to be written.

export function renderAlerts(main) {
  main.innerHTML = `
    <section class="page">
      <h1>Alerts</h1>
      <p class="placeholder">Alerting is not built yet: this page is a placeholder.</p>
    </section>`;
  return () => {};
}
